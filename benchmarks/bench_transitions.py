"""Every transition of a folding world, executed by physics with a demonstrator's noisy clicks.

Usage:
    .venv/bin/python benchmarks/bench_transitions.py [--task tshirt_folding] [--reps 3]
        [--seed 0] [--fresh-library]

For every state and every legal move, `--reps` times: reset the state (from the settled-state
library), click the move's canonical action as a demonstrator would (a few pixels off), execute
it and read the state back. Prints one line per failed try, then one JSON line: tries, failures,
move seconds (mean, p95, max), and the read-back margin: the largest far share of the reached
state's own reference against the smallest of any other state. `--fresh-library` folds the
library again first (and times it) instead of loading the shipped one.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.sim.worlds import make_world
from shared.tasks.base import WorldError


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="tshirt_folding")
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--fresh-library", action="store_true")
    args = parser.parse_args()
    options = {"library": []} if args.fresh_library else {}
    with make_world(args.task, 64, **options) as world:
        task = world.task
        started = time.perf_counter()
        world.library.fill(world)
        library_seconds = time.perf_counter() - started
        rng = np.random.default_rng(args.seed)
        tries = [(s, a) for s in task.all_states() for a in task.legal_actions(s)] * args.reps
        seconds, own, other, failed = [], [], [], []
        for state, action in tqdm(tries, desc="transitions", unit="move"):
            move = task.match(action)
            clicked = world.demonstrated(action, rng)
            expected = task.apply(state, clicked)
            try:
                world.reset(state, rng)
                began = time.perf_counter()
                reached = world.execute(clicked, rng)
                seconds.append(time.perf_counter() - began)
            except WorldError as exc:
                reached, why = None, str(exc)
            if reached == expected:
                shares = world.far_shares()
                own.append(shares[expected])
                other.append(min(v for s, v in shares.items() if s != expected))
                continue
            if reached is not None:
                why = f"reached {task.state_to_json(reached)}"
            failed.append(f"{task.state_to_json(state)} {move.kind} {move.fold}: {why}")
            print("FAILED", failed[-1][:200], file=sys.stderr)
    print(
        json.dumps(
            {
                "task": args.task,
                "tries": len(tries),
                "failed": len(failed),
                "library_seconds": round(library_seconds, 1),
                "move_s": {
                    "mean": round(float(np.mean(seconds)), 2),
                    "p95": round(float(np.percentile(seconds, 95)), 2),
                    "max": round(float(np.max(seconds)), 2),
                },
                "own_far_share_max": round(max(own), 3),
                "other_far_share_min": round(min(other), 3),
            }
        )
    )


if __name__ == "__main__":
    main()
