"""How well the images of a folding world show its states: a state reader trained on resets.

Usage:
    .venv/bin/python benchmarks/bench_state_views.py [--task tshirt_folding] [--size 64]
        [--per-state 24] [--test-per-state 12] [--appearance camera] [--epochs 12] [--seed 0]

Renders every state `--per-state` times from library resets (each a fresh pose and, under
`camera`, a fresh episode look), trains the project's state reader on them, and reads
`--test-per-state` fresh renders of every state. Prints the share read right, overall and split
by the last fold in the task's order (for the T-shirt, `bottom_half`, which hides the sleeves of
folded sides), and each fold's error rate. No moves: what it measures is the images, not the
physics, so it tells whether a model could tell the states apart at that size and look.
"""

from __future__ import annotations

import argparse
import sys
import time
import types
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.sim.state_reader import load_reader, read_states, train_reader
from services.sim.worlds import make_world
from shared.tasks.base import Task, World


def renders(
    world: World, task: Task, per_state: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    images, states = [], []
    for _ in range(per_state):
        for state in task.all_states():
            world.reset(state, rng)
            images.append(world.render())
            states.append(task.state_to_array(state))
    return np.stack(images), np.stack(states)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="tshirt_folding")
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--per-state", type=int, default=24)
    parser.add_argument("--test-per-state", type=int, default=12)
    parser.add_argument("--appearance", default="camera")
    parser.add_argument("--epochs", type=int, default=12)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("runs/state_views_reader"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    started = time.perf_counter()
    with make_world(args.task, args.size, appearance=args.appearance) as world:
        task = world.task
        train_x, train_y = renders(world, task, args.per_state, np.random.default_rng(args.seed))
        test_x, test_y = renders(
            world, task, args.test_per_state, np.random.default_rng(args.seed + 1000)
        )
    half = len(train_x) // 2  # the reader trains on pairs' two images; any split will do
    data = types.SimpleNamespace(
        spec=task.spec, task=task.name, image_size=args.size, manifest={"seed": args.seed},
        image1=train_x[:half], image2=train_x[half:], state1=train_y[:half], state2=train_y[half:],
    )  # fmt: skip
    train_reader(data, args.out, epochs=args.epochs, seed=args.seed, progress=False)
    wrong = read_states(load_reader(args.out), test_x) != test_y
    right = ~wrong.any(1)
    last = test_y[:, -1] == 1
    print(f"{args.task} at {args.size} px, {args.appearance}: trained on {len(train_x)} renders, "
          f"read {len(test_x)} ({time.perf_counter() - started:.0f} s)")  # fmt: skip
    print(f"read right: {100 * right.mean():.1f}%  ({task.folds[-1]} unfolded "
          f"{100 * right[~last].mean():.1f}%, folded {100 * right[last].mean():.1f}%)")  # fmt: skip
    print("error per fold: " + ", ".join(
        f"{fold} {100 * e:.1f}%" for fold, e in zip(task.folds, wrong.mean(0), strict=True)
    ))  # fmt: skip


if __name__ == "__main__":
    main()
