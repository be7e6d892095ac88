"""A flood of large camera frames beside light requests, through the whole stack.

Starts router, services and gateway (`lsr up`'s launcher) on free loopback ports with the shipped
models (or uses a running gateway with --url). Renders box-stacking camera frames through
/render (`"frame": true`) and resizes them to --side px JPEG (quality 90), as a higher-
resolution camera would give them. Then:
1. alone: one client posts frame pairs one after another for --idle-seconds (end-to-end time of
   a pair); then idle: one light client asks /plan from states every --every s as long;
2. flood: --heavy clients post pairs of those frames as fast as they are answered (no client
   waits for Retry-After: a flood) for --seconds, while the light client goes on as in 1 and
   /health is asked every second.
Prints one JSON object: light latency idle and under the flood (p50/p99, errors), heavy answers
by status, Retry-After on every 429/503, heavy pairs served per second, /health's statuses, and
the stack's memory (VmRSS summed over its processes) idle, at most and after.

    .venv/bin/python benchmarks/bench_frame_flood.py [--heavy 8] [--seconds 60] [--side 4096]
        [--encoders 1]
"""

from __future__ import annotations

import argparse
import base64
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

from plan_requests import camera_bytes  # noqa: E402

from services.stack import Stack, StackConfig, free_port  # noqa: E402
from shared.images import decode_image  # noqa: E402
from shared.tasks import get_task  # noqa: E402

TASK = "box_stacking"


def descendants(pid: int) -> list[int]:
    """`pid` and every process under it (an encoder's frames helper among them)."""
    found = [pid]
    for task in Path(f"/proc/{pid}/task").glob("*/children"):
        try:
            children = task.read_text().split()
        except OSError:
            continue
        for child in children:
            found += descendants(int(child))
    return found


def rss_mb(pids: list[int]) -> float:
    """VmRSS summed over the stack's processes and their children."""
    total = 0
    for pid in (p for top in pids for p in descendants(top)):
        try:
            lines = Path(f"/proc/{pid}/status").read_text().splitlines()
        except OSError:
            continue
        total += sum(int(line.split()[1]) for line in lines if line.startswith("VmRSS:"))
    return round(total / 1024, 1)


def ms(values: list[float]) -> dict[str, float] | None:
    if not values:
        return None
    a = np.array(values) * 1e3
    return {k: round(float(np.percentile(a, q)), 1) for k, q in (("p50_ms", 50), ("p99_ms", 99))}


def frames(url: str, count: int, side: int, seed: int) -> tuple[list[str], list[dict]]:
    """`count` JPEG frames (base64) at `side` px a side, and their states as JSON."""
    task = get_task(TASK)
    rng = np.random.default_rng(seed)
    out, states = [], []
    with httpx.Client(base_url=url, timeout=60) as http:
        for i in range(count):
            state = task.state_to_json(task.sample_state(rng))
            body = {"task": TASK, "state": state, "seed": i, "frame": True}
            reply = http.post("/render", json=body)
            reply.raise_for_status()
            frame = decode_image(base64.b64decode(reply.json()["image"]))
            out.append(base64.b64encode(camera_bytes(frame, side=side)).decode())
            states.append(state)
    return out, states


def light_client(url: str, states: list[dict], every_s: float, until: float) -> list:
    """(status, seconds) of /plan from states, one every `every_s`."""
    answers = []
    with httpx.Client(base_url=url, timeout=30) as http:
        i = 0
        while time.monotonic() < until:
            started = time.monotonic()
            body = {
                "task": TASK,
                "start": {"state": states[i % len(states)]},
                "goal": {"state": states[(i + 1) % len(states)]},
            }
            try:
                status = http.post("/plan", json=body).status_code
            except httpx.HTTPError:
                status = 0
            answers.append((status, time.monotonic() - started))
            i += 1
            time.sleep(max(0.0, every_s - (time.monotonic() - started)))
    return answers


def flood(url: str, images: list[str], index: int, until: float) -> list:
    """(status, Retry-After, seconds) of frame pairs posted back to back."""
    answers = []
    with httpx.Client(base_url=url, timeout=30) as http:
        i = index
        while time.monotonic() < until:
            body = {
                "task": TASK,
                "start": {"image": images[i % len(images)]},
                "goal": {"image": images[(i + 1) % len(images)]},
                "include_images": False,
            }
            started = time.monotonic()
            try:
                reply = http.post("/plan", json=body)
                answer = (reply.status_code, reply.headers.get("retry-after"))
            except httpx.HTTPError:
                answer = (0, None)
            answers.append((*answer, time.monotonic() - started))
            i += 1
    return answers


def light_figures(answers: list) -> dict:
    served = [took for status, took in answers if status == 200]
    errors = Counter(status for status, _ in answers if status != 200)
    return {**(ms(served) or {}), "requests": len(answers), "errors": dict(errors)}


def run(url: str, args: argparse.Namespace, pids: list[int]) -> dict:
    images, states = frames(url, args.frames, args.side, args.seed)
    idle_rss = rss_mb(pids)
    one = flood(url, images, 0, time.monotonic() + args.idle_seconds)  # one pair at a time
    idle = light_client(url, states, args.every, time.monotonic() + args.idle_seconds)
    until = time.monotonic() + args.seconds
    memory, health = [], Counter()

    def watch() -> None:
        with httpx.Client(base_url=url, timeout=10) as http:
            while time.monotonic() < until:
                memory.append(rss_mb(pids))
                try:
                    health[http.get("/health").status_code] += 1
                except httpx.HTTPError:
                    health[0] += 1
                time.sleep(1.0)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    with ThreadPoolExecutor(args.heavy + 1) as pool:
        heavy = [pool.submit(flood, url, images, i, until) for i in range(args.heavy)]
        light = light_client(url, states, args.every, until)
        heavy_answers = [a for f in heavy for a in f.result()]
    watcher.join()
    time.sleep(2.0)
    by_status = Counter(status for status, _, _ in heavy_answers)
    refused = [a for a in heavy_answers if a[0] in (429, 503)]
    return {
        "encoders": args.encoders,
        "side": args.side,
        "frame_kb": round(len(images[0]) * 3 / 4 / 1024),
        "heavy_clients": args.heavy,
        "seconds": args.seconds,
        "heavy_alone": {
            **(ms([t for s, _, t in one if s == 200]) or {}),
            "statuses": dict(Counter(s for s, _, _ in one)),
        },
        "light_idle": light_figures(idle),
        "light_flood": light_figures(light),
        "heavy_by_status": dict(sorted(by_status.items())),
        "heavy_served_per_s": round(by_status[200] / args.seconds, 2),
        "heavy_served": ms([t for s, _, t in heavy_answers if s == 200]),
        "refusals_with_retry_after": sum(r is not None for _, r, _ in refused),
        "refusals": len(refused),
        "health": dict(health),
        "rss_mb": {"idle": idle_rss, "max": max(memory, default=None), "after": rss_mb(pids)},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--heavy", type=int, default=8, help="clients posting frames")
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--idle-seconds", type=float, default=20.0)
    parser.add_argument("--every", type=float, default=0.5, help="the light client's period")
    parser.add_argument("--side", type=int, default=4096)
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--encoders", type=int, default=1, help="encoder replicas (lsr up's)")
    parser.add_argument("--url", help="a running gateway (memory not measured); default: a stack")
    args = parser.parse_args()
    if args.url:
        print(json.dumps(run(args.url, args, [])))
        return
    with tempfile.TemporaryDirectory() as logs:
        config = StackConfig(
            port=free_port(), zenoh_port=free_port(), log_dir=Path(logs), encoders=args.encoders
        )
        with Stack(config) as stack:
            stack.start()
            stack.wait_healthy(120)
            pids = [p.pid for p in stack.processes.values()]
            print(json.dumps(run(config.url, args, pids)))


if __name__ == "__main__":
    main()
