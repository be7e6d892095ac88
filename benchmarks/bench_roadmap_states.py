"""Where a model loses its task's states: the latent space, the roadmap's nodes, its edges.

Usage:
    .venv/bin/python benchmarks/bench_roadmap_states.py --model runs/tshirt_2566/vae_l1 \
        --train data/tshirt_folding/train_2566 --test data/tshirt_folding/val [--pairs 1000]

A model folder with vae/ and roadmap/ (node labels from `lsr build-roadmap`), its training data
and held-out data with true states. Prints, in order along the pipeline:
- the latent space alone: the share of held-out images whose nearest training latent (the
  roadmap's metric) shows the same state, a ceiling for any roadmap built from these latents;
- the nodes: how many states have one, which have none, and the share of held-out images whose
  nearest node shows their state;
- the edges: how many join nodes whose states one move links, and the weights of the rest;
- Table I (All / Any / Trans) on all pairs, and on those of them whose two ends show every part
  of their state (`Task.hidden`: for the T-shirt, a folded side's sleeve under the folded
  bottom half).
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.encoder.checkpoint import encode_images, load_vae
from services.planner.build import load_labels
from services.planner.evaluate import evaluate_plans, sample_test_pairs, shows_everything
from services.planner.members import encode_pairs, interleave
from services.planner.regions import metric_p
from services.planner.roadmap import Roadmap
from services.planner.versions import roadmap_dir
from shared.dataset import load_dataset
from shared.tasks import get_task


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, required=True)
    parser.add_argument("--train", type=Path, required=True)
    parser.add_argument("--test", type=Path, required=True)
    parser.add_argument("--pairs", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    vae, _ = load_vae(args.model / "vae")
    roadmap = Roadmap.load(folder := roadmap_dir(args.model))
    train, test = load_dataset(args.train), load_dataset(args.test)
    task = get_task(train.task)
    labels = load_labels(folder, task.name)
    node_states = [task.array_to_state(s) for s in labels.states]
    points = interleave(*encode_pairs(vae, train))
    point_states = [task.array_to_state(s) for s in interleave(train.state1, train.state2)]
    z = interleave(encode_images(vae, test.image1)[0], encode_images(vae, test.image2)[0])
    states_array = interleave(test.state1, test.state2)
    states = [task.array_to_state(s) for s in states_array]
    shows_all = shows_everything(task, states_array)

    def share(hits: np.ndarray) -> str:
        parts = f"{100 * hits.mean():.1f}% of {len(hits)} held-out images"
        if not shows_all.all():
            parts += (
                f" (showing every part {100 * hits[shows_all].mean():.1f}%, "
                f"with hidden parts {100 * hits[~shows_all].mean():.1f}%)"
            )
        return parts

    p = metric_p(roadmap.config.metric)
    _, nearest_point = cKDTree(points).query(z, k=1, p=p)
    latent = np.array([point_states[k] == s for k, s in zip(nearest_point, states, strict=True)])
    print(f"{args.model}: {roadmap.num_nodes} nodes, {len(roadmap.edges)} edges")
    print(f"nearest training latent shows the state: {share(latent)}")

    every = task.all_states()
    per_state = Counter(node_states)
    if every is not None:
        missing = [s for s in every if s not in per_state]
        shown = "; ".join(str(task.state_to_json(s)) for s in missing) or "none"
        print(f"states with a node: {len(every) - len(missing)} of {len(every)}; without: {shown}")
        print(f"nodes per state: {sorted(per_state[s] for s in every)}")
    near = np.asarray(roadmap.nearest_node(z))
    ends = np.array([node_states[k] == s for k, s in zip(near, states, strict=True)])
    print(f"nearest node shows the state: {share(ends)}")

    linked, other = 0, []
    for (a, b), weight in zip(roadmap.edges.tolist(), roadmap.edge_weights.tolist(), strict=True):
        if any(t == node_states[b] for _, t in task.neighbours(node_states[a])):
            linked += 1
        else:
            other.append(weight)
    print(
        f"edges between states one move apart: {linked} of {len(roadmap.edges)}; "
        f"the rest's weights (training pairs): {sorted(other)}"
    )

    pairs = sample_test_pairs(len(z), args.pairs, args.seed)
    visible = pairs[shows_all[pairs].all(1)]
    print("\n| pairs | count | All | Any | Trans |\n| --- | --- | --- | --- | --- |")
    for name, chosen in (("all", pairs), ("both ends show every part", visible)):
        if len(chosen):
            r = evaluate_plans(task.name, roadmap, labels, z, states_array, chosen, 1000)
            figures = " | ".join(f"{r[k]:.1f}" for k in ("all", "any", "trans"))
            print(f"| {name} | {len(chosen)} | {figures} |")


if __name__ == "__main__":
    main()
