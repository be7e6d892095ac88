"""POST /plan latency through the whole stack against the same work in one process.

Starts router, services and gateway (`lsr up`'s launcher) on free loopback ports with the
shipped model, sends image-to-image plan requests at concurrency 1 and 8, and times the
in-process ActionPlanner on the same requests (torch on one thread, as each service runs).

    .venv/bin/python benchmarks/bench_plan_latency.py [--requests 1000] [--pairs 50]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from services.encoder.checkpoint import encode_images, load_vae  # noqa: E402
from services.gateway.planning import decode_b64_image  # noqa: E402
from services.planner.action_plans import ActionPlanner  # noqa: E402
from services.sim.worlds import make_world  # noqa: E402
from services.stack import Stack, StackConfig, free_port  # noqa: E402
from shared.images import PngCache, png_b64  # noqa: E402
from shared.tasks import get_task  # noqa: E402


def percentiles(seconds: list[float]) -> dict[str, float]:
    ms = np.array(seconds) * 1e3
    return {
        "p50_ms": round(float(np.percentile(ms, 50)), 2),
        "p99_ms": round(float(np.percentile(ms, 99)), 2),
        "mean_ms": round(float(ms.mean()), 2),
    }


def request_bodies(pairs: int, size: int, seed: int) -> list[dict]:
    task = get_task("box_stacking")
    rng = np.random.default_rng(seed)
    bodies = []
    with make_world("box_stacking", size) as world:
        for _ in range(pairs):
            images = []
            for state in (task.sample_state(rng), task.sample_state(rng)):
                world.reset(state, rng)
                images.append(png_b64(world.render()))
            bodies.append(
                {
                    "task": "box_stacking",
                    "start": {"image": images[0]},
                    "goal": {"image": images[1]},
                    "max_plans": 8,
                }
            )
    return bodies


def in_process(model: Path, bodies: list[dict], repeats: int) -> dict[str, dict[str, float]]:
    """The gateway's work without transport: decode inputs, plan, encode the PNGs."""
    torch.set_num_threads(1)
    planner = ActionPlanner.from_model_dir(model)
    pngs = PngCache()  # as the gateway does
    encode, core, whole = [], [], []
    for i in range(repeats + len(bodies)):  # the first pass over the bodies warms the caches
        body = bodies[i % len(bodies)]
        t0 = time.perf_counter()
        start = decode_b64_image("start.image", body["start"]["image"], planner.image_size)
        goal = decode_b64_image("goal.image", body["goal"]["image"], planner.image_size)
        t1 = time.perf_counter()
        z, errors = planner.planner.look(np.stack([start, goal]))  # ActionPlanner.plan, split
        t_encoded = time.perf_counter()
        plans = planner.plan_latent(z[0], z[1], body["max_plans"], errors)
        t2 = time.perf_counter()
        json.dumps(
            [
                {"images": [pngs.b64(im) for im in p.images], **p.to_json(planner.task)}
                for p in plans
            ]
        )
        t3 = time.perf_counter()
        if i >= len(bodies):
            encode.append(t_encoded - t1)
            core.append(t2 - t1)
            whole.append(t3 - t0)
    return {
        "encode": percentiles(encode),
        "encode_search_decode_apn": percentiles(core),
        "with_image_codecs": percentiles(whole),
    }


def in_process_throughput(model: Path, bodies: list[dict], requests: int) -> dict[str, float]:
    """What the same cores do in one process: the gateway's work for `requests` requests, by 8
    threads over one planner (torch on one thread each, as a threaded server would run it) and
    by one thread with torch on every core; requests per second of each."""
    planner = ActionPlanner.from_model_dir(model)
    pngs = PngCache()

    def one(body: dict) -> None:
        start = decode_b64_image("start.image", body["start"]["image"], planner.image_size)
        goal = decode_b64_image("goal.image", body["goal"]["image"], planner.image_size)
        plans = planner.plan(start, goal, body["max_plans"])
        task = planner.task
        json.dumps([{"images": [pngs.b64(i) for i in p.images], **p.to_json(task)} for p in plans])

    for body in bodies:  # warm the caches, as the stack's first pass does
        one(body)
    rates = {}
    for name, threads, workers in (("threads_8", 1, 8), ("serial_all_cores", 0, 1)):
        torch.set_num_threads(threads or os.cpu_count() or 1)
        started = time.perf_counter()
        with ThreadPoolExecutor(workers) as pool:
            list(pool.map(one, (bodies[i % len(bodies)] for i in range(requests))))
        rates[name] = round(requests / (time.perf_counter() - started), 1)
    torch.set_num_threads(1)
    return rates


def idle_penalty(model: Path, bodies: list[dict], idle_s: float = 0.012) -> dict[str, dict]:
    """The encoder's forward pass back to back, and after idling as each service does at
    concurrency 1 (it waits ~12 ms for the other stages): on a shared VM, idling costs speed."""
    torch.set_num_threads(1)
    vae, _ = load_vae(model / "vae")
    body = bodies[0]
    images = np.stack([decode_b64_image(k, body[k]["image"], 64) for k in ("start", "goal")])
    timings: dict[str, dict] = {}
    for name, pause in (("back_to_back", 0.0), (f"after_{idle_s * 1e3:.0f}_ms_idle", idle_s)):
        seconds = []
        for _ in range(150):
            time.sleep(pause)
            t0 = time.perf_counter()
            encode_images(vae, images)
            seconds.append(time.perf_counter() - t0)
        timings[name] = percentiles(seconds[20:])
    return timings


def cpu_seconds(stack: Stack) -> dict[str, float]:
    """User + system CPU seconds of each process of the stack so far (Linux /proc)."""
    ticks = os.sysconf("SC_CLK_TCK")
    used = {}
    for name, process in stack.processes.items():
        fields = Path(f"/proc/{process.pid}/stat").read_text().rsplit(")", 1)[1].split()
        used[name] = (int(fields[11]) + int(fields[12])) / ticks  # utime, stime
    return used


def server_timing(header: str) -> dict[str, float]:
    return {name: float(ms) for name, ms in (m.split(";dur=") for m in header.split(", "))}


def through_stack(url: str, bodies: list[dict], requests: int, concurrency: int) -> dict:
    """Latency and throughput; at p50, where the time went (the gateway's Server-Timing)."""
    errors: dict[str, int] = {}
    latencies: list[float] = []
    timings: list[dict[str, float]] = []

    def worker(indices: range) -> None:
        with httpx.Client(base_url=url, timeout=30) as client:
            for i in indices:
                t0 = time.perf_counter()
                try:
                    reply = client.post("/plan", json=bodies[i % len(bodies)])
                    latency = time.perf_counter() - t0
                    ok = reply.status_code == 200 and reply.json()["plans"]
                    key = "ok" if ok else f"http {reply.status_code}"
                except httpx.HTTPError as exc:
                    key = type(exc).__name__
                if key == "ok":
                    latencies.append(latency)
                    timing = server_timing(reply.headers["server-timing"])
                    timings.append({**timing, "http_and_client": latency * 1e3 - timing["gateway"]})
                else:
                    errors[key] = errors.get(key, 0) + 1

    worker(range(len(bodies)))  # warm-up: every node decoded once, connections open
    latencies.clear()
    timings.clear()
    errors.clear()
    started = time.perf_counter()
    chunks = [range(k, requests, concurrency) for k in range(concurrency)]
    with ThreadPoolExecutor(concurrency) as pool:
        list(pool.map(worker, chunks))
    elapsed = time.perf_counter() - started
    return {
        "concurrency": concurrency,
        "requests": requests,
        "errors": sum(errors.values()),
        "error_kinds": errors,
        "requests_per_s": round(requests / elapsed, 1),
        **percentiles(latencies),
        "p50_breakdown_ms": {
            name: round(float(np.median([t[name] for t in timings if name in t])), 2)
            for name in dict.fromkeys(name for t in timings for name in t)
        },
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, default=ROOT / "models" / "box_stacking")
    parser.add_argument("--requests", type=int, default=1000)
    parser.add_argument("--pairs", type=int, default=50, help="distinct start/goal image pairs")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    bodies = request_bodies(args.pairs, 64, args.seed)
    # In-process timings drift from run to run on this shared machine: take them before and
    # after the stack's, and report the ratio against both.
    before = in_process(args.model, bodies, repeats=200)
    print("in process (before):", json.dumps(before), flush=True)
    idle = idle_penalty(args.model, bodies)
    print("encoder forward, 2 images:", json.dumps(idle), flush=True)

    with tempfile.TemporaryDirectory() as logs:
        config = StackConfig(
            port=free_port(), zenoh_port=free_port(), models=(args.model,), log_dir=Path(logs)
        )
        with Stack(config) as stack:
            stack.start()
            print(f"stack healthy in {stack.wait_healthy(90):.1f} s", flush=True)
            one = through_stack(config.url, bodies, 200, 1)
            print("stack, concurrency 1:", json.dumps(one), flush=True)
            cpu = cpu_seconds(stack)
            eight = through_stack(config.url, bodies, args.requests, 8)
            used = cpu_seconds(stack)
            eight["cpu_ms_per_request"] = {
                name: round((used[name] - cpu[name]) * 1e3 / args.requests, 2) for name in used
            }
            print("stack, concurrency 8:", json.dumps(eight), flush=True)
    after = in_process(args.model, bodies, repeats=200)
    print("in process (after):", json.dumps(after), flush=True)
    rate = in_process_throughput(args.model, bodies, args.requests)
    best = max(rate.values())
    print(
        f"in process, requests/s: {json.dumps(rate)}; the stack at concurrency 8 reaches "
        f"{eight['requests_per_s'] / best:.0%} of the better",
        flush=True,
    )
    ratios = [one["p50_ms"] / t["with_image_codecs"]["p50_ms"] for t in (before, after)]
    print(
        "p50 through the stack / in process (same work incl. image codecs): "
        + " and ".join(f"{r:.2f}x" for r in ratios)
    )
    summary = {
        "in_process": [before, after],
        "encoder_idle_penalty": idle,
        "stack_c1": one,
        "stack_c8": eight,
        "in_process_requests_per_s": rate,
        "c8_share_of_in_process": round(eight["requests_per_s"] / best, 3),
    }
    print(json.dumps({**summary, "p50_ratios": [round(r, 2) for r in ratios]}))


if __name__ == "__main__":
    main()
