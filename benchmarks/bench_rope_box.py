"""The rope-box world against its rules: every state laid out, every move done by physics.

Usage:
    .venv/bin/python benchmarks/bench_rope_box.py [--reps 3] [--walks 40] [--steps 30] [--seed 0]

`--reps` times each: every state reset and read back; every legal move from a fresh reset of its
state, executed (a push dragging the rope, a lift carrying it over a pillar) and read back
against the rules' successor. Then `--walks` random walks of `--steps` moves without a reset
between them (as a closed loop acts): a move that reaches no state or the wrong one is counted
and the walk goes on from a fresh reset of the rules' state. Prints each failure, then one JSON
line: tries and failures by kind, and seconds (mean, p95) of a reset and of each kind of move.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.sim.worlds import make_world
from shared.tasks.base import WorldError


def _times(values: list[float]) -> dict[str, float]:
    return {
        "mean_ms": 1000 * float(np.mean(values)),
        "p95_ms": 1000 * float(np.percentile(values, 95)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--walks", type=int, default=40)
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    tries: dict[str, int] = defaultdict(int)
    failed: dict[str, int] = defaultdict(int)
    seconds: dict[str, list[float]] = defaultdict(list)

    def attempt(kind: str, run, expected) -> bool:
        tries[kind] += 1
        began = time.perf_counter()
        try:
            reached, why = run(), ""
        except WorldError as exc:
            reached, why = None, str(exc)
        seconds[kind].append(time.perf_counter() - began)
        if reached != expected:
            failed[kind] += 1
            got = why or task.state_label(reached)
            print(f"{kind}: wanted {task.state_label(expected)}, got {got}", flush=True)
        return reached == expected

    with make_world("rope_box", 64) as world:
        task = world.task
        states = task.all_states()
        for _ in range(args.reps):
            for state in tqdm(states, desc="resets", unit="state"):
                attempt("reset", lambda s=state: world.reset(s, rng), state)
        moves = [(s, a) for s in states for a in task.legal_actions(s)] * args.reps
        for state, action in tqdm(moves, desc="moves", unit="move"):
            world.reset(state, rng)
            attempt(action.kind, lambda a=action: world.execute(a, rng), task.apply(state, action))
        for _ in tqdm(range(args.walks), desc="walks", unit="walk"):
            state = world.reset(states[rng.integers(len(states))], rng)
            for _ in range(args.steps):
                legal = task.legal_actions(state)
                action = legal[rng.integers(len(legal))]
                expected = task.apply(state, action)
                if not attempt(
                    f"walk_{action.kind}", lambda a=action: world.execute(a, rng), expected
                ):
                    world.reset(expected, rng)
                state = expected
    print(
        json.dumps(
            {
                "tries": dict(tries),
                "failures": {k: failed[k] for k in tries},
                "seconds": {k: _times(v) for k, v in seconds.items()},
                "reps": args.reps,
                "seed": args.seed,
            }
        )
    )


if __name__ == "__main__":
    main()
