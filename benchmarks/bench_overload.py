"""Overload: POST /plan from many clients at once, for a while, through the whole stack.

Starts router, services and gateway (`lsr up`'s launcher) on free loopback ports with the
shipped model (or uses a running gateway with --url), renders start and goal images through
/render, then keeps --concurrency clients posting image-to-image /plan requests for --seconds (each
client waits as long as a reply's Retry-After says before its next request).
Prints one JSON object: answers by status, served and shed per second, latency percentiles of
each kind, the slowest answer against the 5 s promise, the gateway's memory (VmRSS) before,
at most and after, and whether it serves normally right after.

    .venv/bin/python benchmarks/bench_overload.py [--concurrency 64] [--seconds 30]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from services.stack import Stack, StackConfig, free_port  # noqa: E402
from shared.tasks import get_task  # noqa: E402

PROMISE_S = 5.0


def rss_mb(pid: int | None) -> float | None:
    if pid is None:
        return None
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return round(int(line.split()[1]) / 1024, 1)
    return None


def bodies(url: str, pairs: int, seed: int, states: bool) -> list[dict]:
    """Image-to-image plan requests, the images rendered by the stack's sim; or, with
    `states`, state-to-state ones (each then costs the sim two renders as well)."""
    task = get_task("box_stacking")
    rng = np.random.default_rng(seed)
    out = []
    if states:
        for _ in range(pairs):
            ends = [{"state": task.state_to_json(task.sample_state(rng))} for _ in range(2)]
            out.append({"task": "box_stacking", "start": ends[0], "goal": ends[1]})
        return out
    with httpx.Client(base_url=url, timeout=30) as http:
        for i in range(pairs):
            images = []
            for state in (task.sample_state(rng), task.sample_state(rng)):
                body = {"task": "box_stacking", "state": task.state_to_json(state), "seed": i}
                reply = http.post("/render", json=body)
                reply.raise_for_status()
                images.append(reply.json()["image"])
            out.append(
                {
                    "task": "box_stacking",
                    "start": {"image": images[0]},
                    "goal": {"image": images[1]},
                }
            )
    return out


def ms(values: list[float]) -> dict[str, float] | None:
    if not values:
        return None
    a = np.array(values) * 1e3
    return {
        "p50_ms": round(float(np.percentile(a, 50)), 1),
        "p99_ms": round(float(np.percentile(a, 99)), 1),
        "max_ms": round(float(a.max()), 1),
    }


def hammer(url: str, work: list[dict], concurrency: int, seconds: float, pid: int | None) -> dict:
    results: list[tuple[int, float]] = []
    lock = threading.Lock()
    stop_at = time.monotonic() + seconds
    memory: list[float] = []

    def client(index: int) -> None:
        with httpx.Client(base_url=url, timeout=30) as http:
            i = index
            while time.monotonic() < stop_at:
                started = time.monotonic()
                retry_after = 0.0
                try:
                    reply = http.post("/plan", json=work[i % len(work)])
                    status = reply.status_code
                    retry_after = float(reply.headers.get("retry-after", 0))
                except httpx.HTTPError:
                    status = 0  # no answer at all
                with lock:
                    results.append((status, time.monotonic() - started))
                i += concurrency
                time.sleep(min(retry_after, max(0.0, stop_at - time.monotonic())))

    def sample_memory() -> None:
        while time.monotonic() < stop_at:
            value = rss_mb(pid)
            if value is not None:
                memory.append(value)
            time.sleep(0.5)

    sampler = threading.Thread(target=sample_memory, daemon=True)
    sampler.start()
    with ThreadPoolExecutor(concurrency) as pool:
        list(pool.map(client, range(concurrency)))
    sampler.join()
    statuses = Counter(status for status, _ in results)
    served = [took for status, took in results if status == 200]
    shed = [took for status, took in results if status in (429, 503)]
    return {
        "requests": len(results),
        "by_status": dict(sorted(statuses.items())),
        "served_per_s": round(len(served) / seconds, 1),
        "shed_per_s": round(len(shed) / seconds, 1),
        "served": ms(served),
        "shed": ms(shed),
        "slowest_s": round(max((took for _, took in results), default=0.0), 3),
        "over_promise": sum(took > PROMISE_S for _, took in results),
        "gateway_rss_max_mb": max(memory, default=None),
    }


def after(url: str, work: list[dict], count: int = 20) -> dict:
    """Sequential requests right after the load: all should be served at normal speed."""
    statuses, times = [], []
    with httpx.Client(base_url=url, timeout=30) as http:
        for body in (work * count)[:count]:
            started = time.monotonic()
            statuses.append(http.post("/plan", json=body).status_code)
            times.append(time.monotonic() - started)
    return {"by_status": dict(Counter(statuses)), "latency": ms(times)}


def run(url: str, args: argparse.Namespace, pid: int | None) -> dict:
    work = bodies(url, args.pairs, args.seed, args.states)
    before = after(url, work)
    rss_before = rss_mb(pid)
    load = hammer(url, work, args.concurrency, args.seconds, pid)
    return {
        "concurrency": args.concurrency,
        "bodies": "states" if args.states else "images",
        "seconds": args.seconds,
        "before": before,
        "load": load,
        "after": after(url, work),
        "gateway_rss_mb": {"before": rss_before, "after": rss_mb(pid)},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--concurrency", type=int, default=64)
    parser.add_argument("--seconds", type=float, default=30.0)
    parser.add_argument("--pairs", type=int, default=16)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--states", action="store_true", help="state-to-state requests")
    parser.add_argument("--url", help="a running gateway; default: start a stack")
    args = parser.parse_args()
    if args.url:
        print(json.dumps(run(args.url, args, None)))
        return
    with tempfile.TemporaryDirectory() as logs:
        config = StackConfig(port=free_port(), zenoh_port=free_port(), log_dir=Path(logs))
        with Stack(config) as stack:
            stack.start()
            stack.wait_healthy(90)
            print(json.dumps(run(config.url, args, stack.processes["gateway"].pid)))


if __name__ == "__main__":
    main()
