"""Memory and start-up of `lsr up` with every shipped task: a process per role, or per role
and task (issue 23's leaner stack). Prints one JSON line per layout and round.

Resident memory is summed over the router, the services and the gateway once `/health` says
200 and one plan per task has been served: RSS (what `ps` shows; shared library pages counted
once per process) and PSS (shared pages split among the processes that map them, so the sum is
what the stack really holds).

    .venv/bin/python benchmarks/bench_stack_memory.py [--rounds 2]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

from services.stack import Stack, StackConfig, free_port, model_task
from shared.settings import shipped_models
from shared.tasks import get_task


def memory_kib(pid: int) -> tuple[int, int]:
    """(RSS, PSS) of one process, in KiB."""
    fields: dict[str, int] = {}
    for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines()[1:]:
        name, value = line.split(":", 1)
        fields[name] = int(value.split()[0])
    return fields["Rss"], fields["Pss"]


def measure(per_task: bool) -> dict:
    models = shipped_models()
    with tempfile.TemporaryDirectory() as logs:
        config = StackConfig(
            port=free_port(),
            zenoh_port=free_port(),
            models=models,
            log_dir=Path(logs),
            process_per_task=per_task,
        )
        with Stack(config) as stack, httpx.Client(base_url=config.url, timeout=30) as http:
            started = time.monotonic()
            stack.start()
            healthy_s = stack.wait_healthy(180)
            planned = {}
            rng = np.random.default_rng(0)
            for name in map(model_task, models):
                task = get_task(name)
                start, goal = (task.state_to_json(task.sample_state(rng)) for _ in range(2))
                body = {"task": name, "start": {"state": start}, "goal": {"state": goal}}
                planned[name] = http.post("/plan", json=body).status_code
            if set(planned.values()) != {200}:
                raise RuntimeError(f"a plan failed: {planned}")
            per_process = {n: memory_kib(p.pid) for n, p in stack.processes.items()}
            total_s = time.monotonic() - started
    return {
        "layout": "process per role and task" if per_task else "process per role",
        "tasks": [model_task(m) for m in models],
        "processes": len(per_process),
        "rss_mib": round(sum(r for r, _ in per_process.values()) / 1024),
        "pss_mib": round(sum(p for _, p in per_process.values()) / 1024),
        "healthy_s": round(healthy_s, 1),
        "up_s": round(total_s, 1),
        "plan_status": planned,
        "rss_mib_by_process": {n: round(r / 1024) for n, (r, _) in per_process.items()},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args()
    for _ in range(args.rounds):
        for per_task in (True, False):
            print(json.dumps(measure(per_task)), flush=True)


if __name__ == "__main__":
    main()
