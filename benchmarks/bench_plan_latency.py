"""POST /plan latency and throughput through the whole stack against the same work in one process.

Starts router, services and gateway (`lsr up`'s launcher) on free loopback ports with the
shipped model, sends image-to-image plan requests at concurrency 1 and 8, and times the
in-process ActionPlanner on the same requests (torch on one thread, as each service runs).
Then, side by side in alternating rounds (this shared VM drifts from run to run): the overhead
at concurrency 1 against the transport floor (`bench_transport_floor.py`), and the stack's
throughput at concurrency 8 against what the same cores do in one process.

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

sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_transport_floor import Floor  # noqa: E402
from plan_requests import percentiles, request_bodies  # noqa: E402

from services.encoder.checkpoint import load_vae  # noqa: E402
from services.gateway.planning import decode_b64_image  # noqa: E402
from services.planner.action_plans import ActionPlanner  # noqa: E402
from services.planner.knowing import look  # noqa: E402
from services.stack import Stack, StackConfig, free_port  # noqa: E402
from shared.images import PngCache  # noqa: E402


class InProcess:
    """The gateway's work without transport: decode inputs, plan, encode the PNGs (with the
    gateway's PNG cache), torch on one thread as each service runs it."""

    def __init__(self, model: Path) -> None:
        torch.set_num_threads(1)
        self.planner = ActionPlanner.from_model_dir(model)
        self.pngs = PngCache()

    def one(self, body: dict) -> tuple[float, float, float]:
        """Seconds of (encoding, encode to APN, the whole request with the image codecs)."""
        planner = self.planner
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
                {"images": [self.pngs.b64(im) for im in p.images], **p.to_json(planner.task)}
                for p in plans
            ]
        )
        return t_encoded - t1, t2 - t1, time.perf_counter() - t0

    def rate(self, bodies: list[dict], requests: int, workers: int, torch_threads: int) -> float:
        """Requests per second of `workers` threads sharing this planner."""
        torch.set_num_threads(torch_threads)
        try:
            started = time.perf_counter()
            with ThreadPoolExecutor(workers) as pool:
                list(pool.map(self.one, (bodies[i % len(bodies)] for i in range(requests))))
            return requests / (time.perf_counter() - started)
        finally:
            torch.set_num_threads(1)


# What the same cores do in one process: 8 threads over one planner (torch on one thread each,
# as a threaded server would run it), and one thread with torch on every core.
IN_PROCESS_MODES = {"threads_8": (8, 1), "serial_all_cores": (1, os.cpu_count() or 1)}


def in_process(model: Path, bodies: list[dict], repeats: int) -> dict[str, dict[str, float]]:
    work = InProcess(model)
    for body in bodies:  # the first pass over the bodies warms the caches
        work.one(body)
    timed = [work.one(bodies[i % len(bodies)]) for i in range(repeats)]
    encode, core, whole = zip(*timed, strict=True)
    return {
        "encode": percentiles(encode),
        "encode_search_decode_apn": percentiles(core),
        "with_image_codecs": percentiles(whole),
    }


def idle_penalty(model: Path, bodies: list[dict], idle_s: float = 0.012) -> dict[str, dict]:
    """The encoder handler's work (`look`: encode and redraw two images) back to back, after
    sleeping and after spinning as long as each service waits at concurrency 1 (~12 ms for the
    other stages), alternately: on this shared VM, time away costs speed, asleep or not."""
    torch.set_num_threads(1)
    vae, _ = load_vae(model / "vae")
    body = bodies[0]
    images = np.stack([decode_b64_image(k, body[k]["image"], 64) for k in ("start", "goal")])

    def spin() -> None:
        until = time.perf_counter() + idle_s
        while time.perf_counter() < until:
            pass

    pauses = {
        "back_to_back": lambda: None,
        f"after_{idle_s * 1e3:.0f}_ms_asleep": lambda: time.sleep(idle_s),
        f"after_{idle_s * 1e3:.0f}_ms_spinning": spin,
    }
    seconds: dict[str, list[float]] = {name: [] for name in pauses}
    for i in range(600):
        name = list(pauses)[i % len(pauses)]
        pauses[name]()
        t0 = time.perf_counter()
        look(vae, images)
        seconds[name].append(time.perf_counter() - t0)
    return {name: percentiles(s[5:]) for name, s in seconds.items()}


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


def through_stack(
    url: str, bodies: list[dict], requests: int, concurrency: int, warm: bool = True
) -> dict:
    """Latency and throughput; at p50, where the time went (the gateway's Server-Timing).
    `warm`: first send every body once (every node decoded, connections open)."""
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

    if warm:
        worker(range(len(bodies)))
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
        "seconds": elapsed,
        **percentiles(latencies),
        "p50_breakdown_ms": {
            name: round(float(np.median([t[name] for t in timings if name in t])), 2)
            for name in dict.fromkeys(name for t in timings for name in t)
        },
    }


def side_by_side(
    model: Path, url: str, bodies: list[dict], rounds: int = 8, per_round: int = 40
) -> dict:
    """The overhead at concurrency 1 against the transport floor, measured side by side: rounds
    of the same requests in process, through the stack, and of the floor's calls (its HTTP
    handler idling as long as the gateway's median so far). Alternating them lets this VM's
    drift (the in-process p50 has moved from 7.7 to 15.9 ms between runs) reach all three alike.
    The first two of each block warm it up and are left out."""
    work = InProcess(model)
    for body in bodies:
        work.one(body)
    local: list[float] = []
    stack: list[float] = []
    gateway: list[float] = []
    parts: dict[str, list[float]] = {"encode_call": [], "small_call": [], "http": []}
    per_round_margin = []
    with Floor() as floor, httpx.Client(base_url=url, timeout=30) as client:
        for _ in range(rounds):
            local += [work.one(bodies[i % len(bodies)])[2] for i in range(per_round)][2:]
            stack_block = []
            for i in range(per_round):
                t0 = time.perf_counter()
                reply = client.post("/plan", json=bodies[i % len(bodies)])
                stack_block.append(time.perf_counter() - t0)
                assert reply.status_code == 200 and reply.json()["plans"], reply.text
                gateway.append(server_timing(reply.headers["server-timing"])["gateway"] / 1e3)
            stack += stack_block[2:]
            idle_s = float(np.median(gateway))
            round_floor = floor.plan_floor(idle_s, per_round)
            for name in parts:
                parts[name].append(round_floor[name])
            overhead = (np.median(stack_block[2:]) - np.median(local[-(per_round - 2) :])) * 1e3
            per_round_margin.append(round(float(overhead - round_floor["plan"]), 2))
    p50 = {name: float(np.median(v)) for name, v in parts.items()}
    floor_ms = p50["encode_call"] + 2 * p50["small_call"] + p50["http"]
    overhead_ms = (np.median(stack) - np.median(local)) * 1e3
    return {
        "in_process_p50_ms": percentiles(local)["p50_ms"],
        "stack_p50_ms": percentiles(stack)["p50_ms"],
        "overhead_ms": round(float(overhead_ms), 2),
        "floor_ms": round(floor_ms, 2),
        "floor_parts_ms": {name: round(v, 2) for name, v in p50.items()},
        "http_handler_idle_ms": round(float(np.median(gateway)) * 1e3, 2),
        "overhead_minus_floor_ms": round(float(overhead_ms - floor_ms), 2),
        "per_round_overhead_minus_floor_ms": per_round_margin,
    }


def throughput_side_by_side(
    model: Path, url: str, bodies: list[dict], rounds: int = 4, per_round: int = 250
) -> dict:
    """The stack at concurrency 8 against the same cores in one process (`IN_PROCESS_MODES`),
    in alternating rounds as `side_by_side`; requests per second over all rounds."""
    work = InProcess(model)
    for body in bodies:  # warm the caches, as the stack's first pass did
        work.one(body)
    seconds = dict.fromkeys(["stack", *IN_PROCESS_MODES], 0.0)
    errors = 0
    for _ in range(rounds):
        through = through_stack(url, bodies, per_round, 8, warm=False)
        seconds["stack"] += through["seconds"]
        errors += through["errors"]
        for mode, (workers, threads) in IN_PROCESS_MODES.items():
            seconds[mode] += per_round / work.rate(bodies, per_round, workers, threads)
    rates = {name: round(rounds * per_round / s, 1) for name, s in seconds.items()}
    best = max(rates[mode] for mode in IN_PROCESS_MODES)
    return {
        "requests_per_s": rates,
        "stack_errors": errors,
        "stack_share_of_better": round(rates["stack"] / best, 3),
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
    print("encoder look, 2 images:", json.dumps(idle), flush=True)

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
            paired = side_by_side(args.model, config.url, bodies)
            print("concurrency 1, side by side:", json.dumps(paired), flush=True)
            rate = throughput_side_by_side(args.model, config.url, bodies)
            print("concurrency 8, side by side:", json.dumps(rate), flush=True)
    after = in_process(args.model, bodies, repeats=200)
    print("in process (after):", json.dumps(after), flush=True)
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
        "c8_side_by_side": rate,
        "c1_side_by_side": paired,
    }
    print(json.dumps({**summary, "p50_ratios": [round(r, 2) for r in ratios]}))


if __name__ == "__main__":
    main()
