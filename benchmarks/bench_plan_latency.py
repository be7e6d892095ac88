"""POST /plan latency and throughput through the whole stack against the same work in one process.

Starts router, services and gateway (`lsr up`'s launcher) on free loopback ports with the
shipped model, sends image-to-image plan requests at concurrency 1 and 8, and times the
in-process ActionPlanner on the same requests (torch on one thread, as each service runs).
Then, side by side in alternating rounds (this shared VM drifts from run to run): the overhead
at concurrency 1 against the transport floor (`bench_transport_floor.py`: a null /plan), and
the stack's throughput at concurrency 8 against what the same cores do in one process.

    .venv/bin/python benchmarks/bench_plan_latency.py [--requests 1000] [--pairs 50]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_transport_floor import CALLS, Floor  # noqa: E402
from plan_requests import percentiles, request_bodies, server_timing  # noqa: E402

from services.encoder.checkpoint import load_vae  # noqa: E402
from services.gateway.planning import decode_b64_image  # noqa: E402
from services.planner.action_plans import ActionPlanner  # noqa: E402
from services.planner.knowing import look  # noqa: E402
from services.stack import Stack, StackConfig, free_port  # noqa: E402
from shared.images import PngCache  # noqa: E402


class InProcess:
    """The gateway's work without transport: decode inputs, plan, encode the PNGs (with the
    gateway's PNG cache), torch on one thread as each service runs it."""

    def __init__(self, model: Path, bodies: list[dict]) -> None:
        torch.set_num_threads(1)
        self.planner = ActionPlanner.from_model_dir(model)
        self.pngs = PngCache()
        self.bodies = bodies
        for body in bodies:  # decodes every node and PNG once, as the stack's first pass does
            self.one(body)

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

    def run(self, requests: int) -> list[tuple[float, float, float]]:
        return [self.one(self.bodies[i % len(self.bodies)]) for i in range(requests)]

    def seconds(self, requests: int, workers: int, torch_threads: int) -> float:
        """How long `workers` threads sharing this planner take for `requests` requests."""
        threads = torch.get_num_threads()
        torch.set_num_threads(torch_threads)
        try:
            started = time.perf_counter()
            bodies = (self.bodies[i % len(self.bodies)] for i in range(requests))
            with ThreadPoolExecutor(workers) as pool:
                list(pool.map(self.one, bodies))
            return time.perf_counter() - started
        finally:
            torch.set_num_threads(threads)


# What the same cores do in one process: 8 threads over one planner (torch on one thread each,
# as a threaded server would run it), and one thread with torch on every core.
CORES = len(os.sched_getaffinity(0))
IN_PROCESS_MODES = {"threads_8": (8, 1), "serial_all_cores": (1, CORES)}


def in_process(model: Path, bodies: list[dict], repeats: int) -> dict[str, dict[str, float]]:
    """Percentiles of `InProcess.one`'s parts over `repeats` requests after the warm-up."""
    encode, core, whole = zip(*InProcess(model, bodies).run(repeats), strict=True)
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
    names = list(pauses)
    for i in range(600):
        name = names[i % len(names)]
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


def through_stack(
    url: str, bodies: list[dict], requests: int, concurrency: int, warm: bool = True
) -> dict:
    """Latency and throughput; at p50, where the time went (the gateway's Server-Timing).
    `warm`: first send every body once (every node decoded, connections open)."""
    errors: dict[str, int] = {}
    latencies: list[float] = []
    sizes: list[int] = []
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
                    sizes.append(len(reply.content))
                    timing = server_timing(reply.headers["server-timing"])
                    timings.append({**timing, "http_and_client": latency * 1e3 - timing["gateway"]})
                else:
                    errors[key] = errors.get(key, 0) + 1

    if warm:
        worker(range(len(bodies)))
    latencies.clear()
    sizes.clear()
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
        "ok": len(latencies),
        "reply_bytes_p50": int(np.median(sizes)) if sizes else 0,
        **percentiles(latencies),
        "p50_breakdown_ms": {
            name: round(float(np.median([t[name] for t in timings if name in t])), 2)
            for name in dict.fromkeys(name for t in timings for name in t)
        },
    }


def side_by_side(
    model: Path,
    url: str,
    bodies: list[dict],
    handler_ms: dict[str, float],
    reply_bytes: int,
    rounds: int = 8,
    per_round: int = 40,
) -> dict:
    """The overhead at concurrency 1 against the transport floor (`bench_transport_floor.py`: a
    null /plan whose services sleep `handler_ms`, replying `reply_bytes`), measured in rounds
    of `per_round` requests in process, through the stack and through the null /plan, in turn
    (each round starts with the next), so that this VM's drift reaches all three alike. The
    first two requests of each block warm it and are left out."""
    work = InProcess(model, bodies)
    warm = 2
    local: list[tuple[float, float, float]] = []
    stack: list[float] = []
    stack_timing: list[dict[str, float]] = []
    floor_parts: dict[str, list[float]] = {"plan": [], "calls": [], "http": []}
    margins: list[float] = []
    with Floor(handler_ms, reply_bytes) as floor, httpx.Client(base_url=url, timeout=30) as client:

        def through_stack_block() -> None:
            latencies = []
            for i in range(per_round):
                t0 = time.perf_counter()
                reply = client.post("/plan", json=bodies[i % len(bodies)])
                latency = time.perf_counter() - t0
                assert reply.status_code == 200 and reply.json()["plans"], reply.text
                if i >= warm:
                    latencies.append(latency)
                    timing = server_timing(reply.headers["server-timing"])
                    stack_timing.append(
                        {**timing, "http_and_client": latency * 1e3 - timing["gateway"]}
                    )
            stack.extend(latencies)

        def in_process_block() -> None:
            local.extend(work.run(per_round)[warm:])

        def floor_block() -> None:
            for name, seconds in floor.plans(per_round).items():
                floor_parts[name].extend(seconds[warm:])

        blocks = [in_process_block, through_stack_block, floor_block]
        for r in range(rounds):
            for block in blocks[r % 3 :] + blocks[: r % 3]:
                block()
            kept = per_round - warm
            overhead = np.median(stack[-kept:]) - np.median([w for _, _, w in local[-kept:]])
            margins.append(round(float(overhead - np.median(floor_parts["plan"][-kept:])) * 1e3, 2))

    def p50(seconds: list[float]) -> float:
        return round(float(np.median(seconds)) * 1e3, 2)

    def timing_p50(part: Callable[[dict[str, float]], float]) -> float:
        return round(float(np.median([part(t) for t in stack_timing])), 2)

    whole = [w for _, _, w in local]
    overhead_ms = p50(stack) - p50(whole)
    return {
        "in_process_p50_ms": p50(whole),
        "stack_p50_ms": p50(stack),
        "overhead_ms": round(overhead_ms, 2),
        "floor_ms": p50(floor_parts["plan"]),
        "overhead_minus_floor_ms": round(overhead_ms - p50(floor_parts["plan"]), 2),
        "per_round_overhead_minus_floor_ms": margins,
        "median_of_rounds_ms": round(float(np.median(margins)), 2),
        # where the difference lies, from the same rounds (ms, p50; no propose call when start
        # and goal match one node)
        "floor_calls_beyond_handlers_ms": p50(floor_parts["calls"]),
        "stack_calls_beyond_handlers_ms": timing_p50(
            lambda t: sum(t.get(c, 0.0) - t.get(f"{c}-handler", 0.0) for c in CALLS)
        ),
        "floor_http_ms": p50(floor_parts["http"]),
        "stack_http_and_client_ms": timing_p50(lambda t: t["http_and_client"]),
        "in_process_encode_ms": p50([e for e, _, _ in local]),
        "stack_encode_handler_ms": timing_p50(lambda t: t["encode-handler"]),
        "in_process_search_and_apn_ms": p50([c - e for e, c, _ in local]),
        "stack_paths_and_propose_handlers_ms": timing_p50(
            lambda t: t["paths-handler"] + t.get("propose-handler", 0.0)
        ),
        "in_process_image_codecs_ms": p50([w - c for _, c, w in local]),
        "stack_gateway_beyond_calls_ms": timing_p50(
            lambda t: t["gateway"] - sum(t.get(c, 0.0) for c in CALLS)
        ),
    }


def throughput_side_by_side(
    model: Path, url: str, bodies: list[dict], rounds: int = 4, per_round: int = 250
) -> dict:
    """The stack at concurrency 8 against the same cores in one process (`IN_PROCESS_MODES`),
    in rounds that each start with the next of them, as `side_by_side`; requests per second
    over all rounds (the stack's: answered ones only)."""
    work = InProcess(model, bodies)
    seconds = dict.fromkeys(["stack", *IN_PROCESS_MODES], 0.0)
    served = errors = 0

    def stack_round() -> None:
        nonlocal served, errors
        through = through_stack(url, bodies, per_round, 8, warm=False)
        seconds["stack"] += through["seconds"]
        served += through["ok"]
        errors += through["errors"]

    def in_process_round(mode: str) -> None:
        workers, threads = IN_PROCESS_MODES[mode]
        seconds[mode] += work.seconds(per_round, workers, threads)

    turns = [stack_round, *(lambda m=m: in_process_round(m) for m in IN_PROCESS_MODES)]
    for r in range(rounds):
        for turn in turns[r % len(turns) :] + turns[: r % len(turns)]:
            turn()
    rates = {mode: round(rounds * per_round / seconds[mode], 1) for mode in IN_PROCESS_MODES}
    rates["stack"] = round(served / seconds["stack"], 1)
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
            handler_ms = {op: one["p50_breakdown_ms"][f"{op}-handler"] for op in CALLS}
            paired = side_by_side(
                args.model, config.url, bodies, handler_ms, one["reply_bytes_p50"]
            )
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
