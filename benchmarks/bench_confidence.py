"""How often plans at a confidence are valid (issue 21): a reliability table from held-out data.

Usage:
    .venv/bin/python benchmarks/bench_confidence.py --model models/box_stacking \
        --test data/box_stacking/test [--pairs 1000] [--seed 0] [--max-plans 8]

Plans between seeded start/goal pairs of unseen test images, as `/plan` makes them (refusal on:
pairs with an unknown end get no plan and are counted apart). A plan is valid when its first
node shows the start image's true state, its last the goal's, and every APN action, applied by
the task's rules to one node's state, gives the next node's. A plan's confidence is the product
of its actions' confidences (`confidence` in every plan reply). Prints markdown: plans and valid
share per confidence band, then for each cut the share of plans at or above it and how many of
those were valid.
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.planner.action_plans import ActionPlanner
from services.planner.build import load_labels
from services.planner.eval_vfm import load_test_images
from services.planner.evaluate import action_leads, sample_test_pairs
from shared.plans import UnknownImageError

BANDS = (0.0, 0.5, 0.8, 0.9, 0.95, 0.99, 1.0 + 1e-9)
CUTS = (0.5, 0.8, 0.9, 0.95, 0.99)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, required=True)
    parser.add_argument("--test", type=Path, required=True)
    parser.add_argument("--pairs", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-plans", type=int, default=8)
    args = parser.parse_args()

    planner = ActionPlanner.from_model_dir(args.model)
    task = planner.task
    labels = load_labels(args.model / "roadmap", task.name)
    node_states = [task.array_to_state(s) for s in labels.states]
    images, states, _ = load_test_images(args.test)
    z, errors = planner.planner.look(images)
    confidence, valid = [], []
    refused = no_plan = 0
    for i, j in tqdm(sample_test_pairs(len(images), args.pairs, args.seed), desc="pairs"):
        start, goal = task.array_to_state(states[i]), task.array_to_state(states[j])
        try:
            plans = planner.plan_latent(z[i], z[j], args.max_plans, errors[[i, j]])
        except UnknownImageError:
            refused += 1
            continue
        no_plan += not plans
        for plan in plans:
            path = [node_states[n] for n in plan.nodes]
            ok = path[0] == start and path[-1] == goal
            ok = ok and all(
                action_leads(task, a, action, b)
                for (a, b), action in zip(itertools.pairwise(path), plan.actions, strict=True)
            )
            confidence.append(plan.confidence)
            valid.append(ok)
    c, v = np.array(confidence), np.array(valid, bool)
    print(f"{args.model} on {args.test}: {args.pairs} pairs (seed {args.seed}), {len(c)} plans, "
          f"{refused} pairs refused, {no_plan} without a path; {100 * v.mean():.1f}% of plans "
          "valid\n")  # fmt: skip
    print("| plan confidence | plans | valid |\n| --- | --- | --- |")
    for low, high in itertools.pairwise(BANDS):
        band = (c >= low) & (c < high)
        shown = f"{low:g} - {min(high, 1.0):g}"
        rate = f"{100 * v[band].mean():.1f}%" if band.any() else "-"
        print(f"| {shown} | {int(band.sum())} | {rate} |")
    print("\n| cut: plans at or above | share of plans | of those valid | valid below the cut |")
    print("| --- | --- | --- | --- |")
    for cut in CUTS:
        kept = c >= cut
        above = f"{100 * v[kept].mean():.1f}%" if kept.any() else "-"
        below = f"{100 * v[~kept].mean():.1f}%" if (~kept).any() else "-"
        print(f"| {cut:g} | {100 * kept.mean():.1f}% | {above} | {below} |")


if __name__ == "__main__":
    main()
