"""How fast a deformable world answers: resets, data generation, the closed loop, the stack.

Usage (each part prints one JSON line; `--parts` picks them, default all):
    .venv/bin/python benchmarks/bench_fast_worlds.py [--task cloth_folding]
        [--parts reset datagen closed_loop stack] [--pairs 200] [--renders 20]
        [--datagen-pairs 200] [--closed-loop 20] [--seed 0]

- reset: one process, `world.reset(state)` for the flat state and for each number of folds.
- datagen: `lsr data generate`'s `generate` with 2 workers: tuples per second.
- closed_loop: `lsr eval system`'s loop in one process with the shipped model: seconds a task.
- stack: `lsr up`'s launcher with the shipped model on free loopback ports; `POST /render` of
  the flat and of the fully folded state (p50 / p95, failures), then `POST /plan` from states
  for `--pairs` random start/goal pairs, one at a time (failures: any answer but 200 with plans).
Run it from the checkout to measure (it imports that checkout's code, so a worktree of an older
commit measures the older code the same way).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from services.sim.worlds import make_world  # noqa: E402
from shared.tasks import get_task  # noqa: E402


def stats(seconds: list[float]) -> dict[str, float | None]:
    if not seconds:
        return {"p50_ms": None, "p95_ms": None, "max_ms": None}
    ms = np.array(seconds) * 1e3
    return {
        "p50_ms": round(float(np.percentile(ms, 50)), 1),
        "p95_ms": round(float(np.percentile(ms, 95)), 1),
        "max_ms": round(float(ms.max()), 1),
    }


def part_reset(task_name: str, seed: int) -> dict:
    task = get_task(task_name)
    rng = np.random.default_rng(seed)
    by_folds: dict[int, list[float]] = {}
    with make_world(task_name, 64) as world:
        for _ in range(2):  # the second round: what a warm process pays
            for state in task.all_states():
                started = time.perf_counter()
                world.reset(state, rng)
                by_folds.setdefault(len(state), []).append(time.perf_counter() - started)
    return {
        "part": "reset",
        "task": task_name,
        "by_folds": {k: stats(v) for k, v in sorted(by_folds.items())},
    }


def part_datagen(task_name: str, pairs: int, seed: int) -> dict:
    from services.sim.datagen import GenerateConfig, generate

    with tempfile.TemporaryDirectory() as tmp:
        cfg = GenerateConfig(task=task_name, pairs=pairs, seed=seed, workers=2)
        started = time.perf_counter()
        result = generate(cfg, Path(tmp) / "data", progress=False)
        wall = time.perf_counter() - started
    return {
        "part": "datagen",
        "task": task_name,
        "pairs": pairs,
        "workers": 2,
        "wall_s": round(wall, 1),
        "tuples_per_s": round(pairs / wall, 3),
        "physics_retries": result["physics_retries"],
    }


def part_closed_loop(model: Path, pairs: int, seed: int) -> dict:
    import torch

    from services.planner.action_plans import ActionPlanner
    from services.sim.closed_loop import evaluate_system

    torch.set_num_threads(1)
    planner = ActionPlanner.from_model_dir(model)
    with make_world(planner.task.name, planner.image_size) as world:
        started = time.perf_counter()
        result = evaluate_system(planner, world, planner.task, pairs, seed=seed, progress=False)
        wall = time.perf_counter() - started
    return {
        "part": "closed_loop",
        "task": planner.task.name,
        "pairs": pairs,
        "success": result["success"],
        "seconds_per_task": round(wall / pairs, 3),
        "actions_executed": result["actions_executed"],
    }


def part_stack(model: Path, renders: int, pairs: int, seed: int) -> dict:
    from services.stack import Stack, StackConfig, free_port, model_task

    task = get_task(model_task(model))
    states = task.all_states()
    full = max(states, key=len)
    rng = np.random.default_rng(seed)
    with tempfile.TemporaryDirectory() as logs:
        config = StackConfig(
            port=free_port(), zenoh_port=free_port(), models=(model,), log_dir=Path(logs)
        )
        with Stack(config) as stack, httpx.Client(base_url=config.url, timeout=60) as http:
            stack.start()
            stack.wait_healthy(300)
            render: dict[str, dict] = {}
            for name, state in (("flat", states[0]), ("all_folds", full)):
                times, failures = [], []
                warm = {"task": task.name, "state": task.state_to_json(state), "seed": renders}
                http.post("/render", json=warm)  # untimed: a process's first render sets up EGL
                for i in range(renders):
                    body = {"task": task.name, "state": task.state_to_json(state), "seed": i}
                    started = time.perf_counter()
                    reply = http.post("/render", json=body)
                    times.append(time.perf_counter() - started)
                    if reply.status_code != 200:
                        failures.append(f"{reply.status_code} {reply.text[:120]}")
                render[name] = {**stats(times), "failures": len(failures), "first": failures[:1]}
            flat, folded = render["flat"]["p95_ms"], render["all_folds"]["p95_ms"]
            times, failures = [], []
            for i in range(pairs):
                a, b = rng.choice(len(states), 2, replace=False)
                body = {
                    "task": task.name,
                    "start": {"state": task.state_to_json(states[a])},
                    "goal": {"state": task.state_to_json(states[b])},
                    "include_images": False,
                }
                started = time.perf_counter()
                reply = http.post("/plan", json=body)
                times.append(time.perf_counter() - started)
                if reply.status_code != 200 or not reply.json().get("plans"):
                    failures.append(f"#{i} {reply.status_code} {reply.text[:120]}")
    return {
        "part": "stack",
        "task": task.name,
        "render": render,
        "render_p95_ratio": round(folded / flat, 2) if flat and folded else None,
        "plan_from_states": {
            "pairs": pairs,
            **stats(times),
            "failures": len(failures),
            "first": failures[:3],
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--task", default="cloth_folding")
    parser.add_argument("--model", type=Path, help="default: models/TASK")
    parser.add_argument(
        "--parts",
        nargs="+",
        default=["reset", "datagen", "closed_loop", "stack"],
        choices=["reset", "datagen", "closed_loop", "stack"],
    )
    parser.add_argument("--pairs", type=int, default=200, help="/plan requests from states")
    parser.add_argument("--renders", type=int, default=20, help="/render requests per state")
    parser.add_argument("--datagen-pairs", type=int, default=200)
    parser.add_argument("--closed-loop", type=int, default=20, help="closed-loop tasks")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    model = args.model or ROOT / "models" / args.task
    for part in args.parts:
        if part == "reset":
            result = part_reset(args.task, args.seed)
        elif part == "datagen":
            result = part_datagen(args.task, args.datagen_pairs, args.seed)
        elif part == "closed_loop":
            result = part_closed_loop(model, args.closed_loop, args.seed)
        else:
            result = part_stack(model, args.renders, args.pairs, args.seed)
        print(json.dumps(result), flush=True)


if __name__ == "__main__":
    main()
