"""What /plan's transport costs with no work at all: the floor under the stack's overhead.

Times, in separate processes as in the stack:
- a service call through a zenoh router (`lsr router`) to a `Server` whose handler computes
  nothing: the encode call's messages (two 64 px images in, two latents out), with the same
  12 ms of idling between calls as each service sees at concurrency 1, and back to back;
- an HTTP POST of a real /plan body (16 KB) to a FastAPI route under uvicorn that validates it
  as `PlanRequest` and answers a prebuilt 100 KB body (a plan's PNGs), with httpx as client.

/plan makes three sequential service calls and one HTTP exchange; at most 1.5x the in-process
time leaves the stack half the in-process time for all of them.

    .venv/bin/python benchmarks/bench_transport_floor.py
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_plan_latency import percentiles, request_bodies  # noqa: E402

from services.gateway.schemas import PlanRequest  # noqa: E402
from services.stack import free_port  # noqa: E402
from shared.bus import (  # noqa: E402
    BusConfig,
    Server,
    call,
    close_quietly,
    open_session,
    service_key,
)
from shared.messages import EncodeReply, EncodeRequest, WireArray, unpack  # noqa: E402

REPLY_BYTES = 100_000


def serve_echo(endpoint: str) -> None:
    session = open_session(BusConfig(connect=[endpoint], open_timeout_s=10))
    server = Server(session, "echo", "floor")

    def encode(payload: bytes) -> EncodeReply:
        images = unpack(payload, EncodeRequest).images.numpy()
        return EncodeReply(latents=WireArray.of(np.zeros((len(images), 64), np.float32)))

    server.serve(service_key("echo", "t", "encode"), encode)
    print("ready", flush=True)
    sys.stdin.read()  # until the parent closes our stdin
    server.close()
    close_quietly(session)


def serve_http(port: int) -> None:
    import uvicorn
    from fastapi import FastAPI
    from fastapi.responses import Response

    app = FastAPI()
    body = json.dumps({"plans": [{"images": ["A" * (REPLY_BYTES // 7)] * 7}]})

    @app.post("/plan")
    def plan(request: PlanRequest) -> Response:
        return Response(body, media_type="application/json")

    uvicorn.run(app, host="127.0.0.1", port=port, log_level="warning")


def spawn(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, __file__, *args], stdin=subprocess.PIPE, stdout=subprocess.PIPE
    )


def time_calls(endpoint: str, idle_s: float, n: int = 300) -> dict:
    session = open_session(BusConfig(connect=[endpoint], open_timeout_s=10))
    images = np.zeros((2, 64, 64, 3), np.uint8)
    request = EncodeRequest(task="t", images=WireArray.of(images))
    round_trips, handlers = [], []
    try:
        for _ in range(n):
            time.sleep(idle_s)
            pending = call(session, "echo", "t", "encode", request, EncodeReply)
            pending.result()
            round_trips.append(pending.timing.round_trip_ms / 1e3)
            handlers.append(pending.timing.handler_ms / 1e3)
    finally:
        close_quietly(session)
    return {"round_trip": percentiles(round_trips[20:]), "handler": percentiles(handlers[20:])}


def time_http(port: int, n: int = 300) -> dict:
    bodies = request_bodies(5, 64, seed=0)
    seconds = []
    with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=10) as client:
        deadline = time.monotonic() + 20
        while True:  # until uvicorn listens
            try:
                client.post("/plan", json=bodies[0])
                break
            except httpx.TransportError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        for i in range(n):
            t0 = time.perf_counter()
            reply = client.post("/plan", json=bodies[i % len(bodies)])
            seconds.append(time.perf_counter() - t0)
            assert reply.status_code == 200 and len(reply.content) > REPLY_BYTES * 0.9, reply.text
    return percentiles(seconds[20:])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--role", choices=["echo", "http"], help=argparse.SUPPRESS)
    parser.add_argument("--endpoint", help=argparse.SUPPRESS)
    parser.add_argument("--port", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.role == "echo":
        return serve_echo(args.endpoint)
    if args.role == "http":
        return serve_http(args.port)

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = subprocess.Popen(
        [sys.executable, "-m", "services.cli", "router", "--listen", endpoint], cwd=ROOT
    )
    echo = spawn("--role", "echo", "--endpoint", endpoint)
    http_port = free_port()
    http = spawn("--role", "http", "--port", str(http_port))
    try:
        assert echo.stdout is not None and echo.stdout.readline().strip() == b"ready"
        time.sleep(0.5)  # the router learns the queryable
        results = {
            "zenoh_call_after_12_ms_idle": time_calls(endpoint, idle_s=0.012),
            "zenoh_call_back_to_back": time_calls(endpoint, idle_s=0.0),
            "http_post_16kb_in_100kb_out": time_http(http_port),
        }
    finally:
        for process in (echo, http, router):
            process.terminate()
            process.wait(10)
    for name, figures in results.items():
        print(f"{name}: {json.dumps(figures)}")
    idle_call = results["zenoh_call_after_12_ms_idle"]
    call_ms = idle_call["round_trip"]["p50_ms"] - idle_call["handler"]["p50_ms"]
    http_ms = results["http_post_16kb_in_100kb_out"]["p50_ms"]
    print(
        f"transport floor of one /plan (3 calls beyond their handlers + HTTP), p50: "
        f"{3 * call_ms + http_ms:.2f} ms (3 x {call_ms:.2f} + {http_ms:.2f})"
    )


if __name__ == "__main__":
    main()
