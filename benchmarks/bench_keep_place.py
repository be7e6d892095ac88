"""Where a closed loop re-plans from: the node its last step was meant to reach, or the image's.

For every unseen test image and every other node taken as the expected one, `knowing.keep_place`
decides; a node whose labelled view is not the image's is a wrong place to plan from, one whose
view is the image's (a grown roadmap's state lies over several nodes) a right one. Prints how
often a wrong expected node is kept and a right one given up, by knowing alone (the rule before
2026-12-05) and with Algorithm 1's test (`services/planner/places.py`).

Usage:
  python benchmarks/bench_keep_place.py --model models/tshirt_folding \
      --test data/tshirt_smooth/test_camera
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from services.planner.action_plans import ActionPlanner
from services.planner.build import load_labels
from services.planner.knowing import keep_place
from services.planner.versions import roadmap_dir
from shared.dataset import load_dataset


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, required=True)
    parser.add_argument("--test", type=Path, required=True)
    args = parser.parse_args()
    planner = ActionPlanner.from_model_dir(args.model)
    task, vp = planner.task, planner.planner
    if vp.calibration is None or vp.places is None:
        raise SystemExit(f"{args.model}: needs a calibrated roadmap with its members")
    labels = load_labels(roadmap_dir(args.model), task.name)
    node_view = [task.view(task.array_to_state(s)) for s in labels.states]
    data = load_dataset(args.test)
    images = np.concatenate([data.image1, data.image2])
    states = np.concatenate([data.state1, data.state2])
    z, _ = vp.look(images)
    near = np.atleast_1d(vp.roadmap.nearest_node(z))
    counts = {k: 0 for k in ("wrong", "wrong_kept_before", "wrong_kept", "right",
                             "right_kept_before", "right_kept")}  # fmt: skip
    for latent, state, start in zip(z, states, near, strict=True):
        view = task.view(task.array_to_state(state))
        for expect in range(vp.roadmap.num_nodes):
            if expect == start:
                continue
            kind = "right" if node_view[expect] == view else "wrong"
            before = keep_place(vp.roadmap, vp.calibration, latent, int(start), expect)
            after = keep_place(vp.roadmap, vp.calibration, latent, int(start), expect, vp.places)
            counts[kind] += 1
            counts[f"{kind}_kept_before"] += before == expect
            counts[f"{kind}_kept"] += after == expect
    views = [task.view(task.array_to_state(s)) for s in states]
    shown = [node_view[n] == v for n, v in zip(near, views, strict=True)]
    result = {"images": len(images), "nearest_shows_the_view": 100.0 * float(np.mean(shown))}
    print(json.dumps(result | counts))


if __name__ == "__main__":
    main()
