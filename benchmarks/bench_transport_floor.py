"""What /plan's transport costs with no work at all: the floor under the stack's overhead.

A null /plan: the processes of the stack (a router; an encoder, a planner and an APN, each its
own `Server`; a gateway under uvicorn), whose handlers sleep instead of working. The gateway's
route validates a real /plan body as `PlanRequest`, makes the three calls one after the other
(the encode call's messages, then 2 KB ones as paths and propose send) and answers a body of a
plan reply's size. Each service sleeps as long as the stack's handler takes, so that every
process idles as it does in the stack at concurrency 1 (idle threads wake slower on a shared
VM). The floor is the client's latency less those sleeps, as the replies report them.

`bench_plan_latency.py` measures this floor beside the stack, with the stack's own handler
times and reply size.

    .venv/bin/python benchmarks/bench_transport_floor.py [--handler-ms 9 1 0.8] [--reply-kb 55]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import zenoh

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from plan_requests import percentiles, request_bodies, server_timing  # noqa: E402

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

# The three calls of /plan in order, and the images each sends: the encode call's own size, and
# 2 KB for paths and propose (their latents measured 1.0-3.6 KB).
CALLS = {"encode": (2, 64, 64, 3), "paths": (1, 26, 26, 3), "propose": (1, 26, 26, 3)}


def serve_echo(endpoint: str, operation: str, sleep_ms: float) -> None:
    session = open_session(BusConfig(connect=[endpoint], open_timeout_s=10))
    server = Server(session, operation, "floor")

    def echo(payload: bytes) -> EncodeReply:
        rows = len(unpack(payload, EncodeRequest).images.numpy())
        time.sleep(sleep_ms / 1e3)
        return EncodeReply(
            latents=WireArray.of(np.zeros((rows, 64), np.float32)),
            errors=WireArray.of(np.zeros((rows, 3), np.float32)),
        )

    server.serve(service_key(operation, "t", operation), echo)
    print("ready", flush=True)
    sys.stdin.read()  # until the parent closes our stdin
    server.close()
    close_quietly(session)


def serve_gateway(endpoint: str, port: int, reply_bytes: int) -> None:
    import uvicorn
    from fastapi import FastAPI
    from fastapi.responses import Response

    session: zenoh.Session = open_session(BusConfig(connect=[endpoint], open_timeout_s=10))
    app = FastAPI()
    body = json.dumps({"plans": [{"images": ["A" * (reply_bytes // 7)] * 7}]})
    requests = {
        operation: EncodeRequest(task="t", images=WireArray.of(np.zeros(shape, np.uint8)))
        for operation, shape in CALLS.items()
    }

    @app.post("/plan")
    def plan(request: PlanRequest) -> Response:
        timings = []
        for operation, message in requests.items():
            pending = call(session, operation, "t", operation, message, EncodeReply)
            pending.result()
            timings.append(pending.timing)
        metrics = ", ".join(
            f"{t.operation};dur={t.round_trip_ms:.3f}, {t.operation}-handler;dur={t.handler_ms:.3f}"
            for t in timings
        )
        return Response(body, media_type="application/json", headers={"Server-Timing": metrics})

    uvicorn.run(app, host="127.0.0.1", port=port, log_level="warning")
    close_quietly(session)


def spawn(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, __file__, *args], stdin=subprocess.PIPE, stdout=subprocess.PIPE
    )


def stop(processes: list[subprocess.Popen]) -> None:
    for process in processes:
        with contextlib.suppress(OSError):
            if process.stdin is not None:
                process.stdin.close()  # an echo service stops when its stdin closes
        process.terminate()
    for process in processes:
        try:
            process.wait(10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        if process.stdout is not None:
            process.stdout.close()


class Floor:
    """The null /plan's processes, from entering until leaving."""

    def __init__(self, handler_ms: dict[str, float], reply_bytes: int) -> None:
        self.handler_ms = handler_ms
        self.reply_bytes = reply_bytes
        self.processes: list[subprocess.Popen] = []
        self.client: httpx.Client | None = None
        self.bodies = request_bodies(5, 64, seed=0)

    def __enter__(self) -> Floor:
        try:
            self._start()
        except BaseException:
            self.__exit__()
            raise
        return self

    def _start(self) -> None:
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        port = free_port()
        self.processes.append(
            subprocess.Popen(
                [sys.executable, "-m", "services.cli", "router", "--listen", endpoint],
                cwd=ROOT,
                stdout=subprocess.DEVNULL,
            )
        )
        echoes = [
            spawn(
                "--role",
                "echo",
                "--endpoint",
                endpoint,
                "--operation",
                operation,
                "--sleep-ms",
                str(self.handler_ms[operation]),
            )
            for operation in CALLS
        ]
        self.processes += echoes
        for echo in echoes:
            assert echo.stdout is not None and echo.stdout.readline().strip() == b"ready"
        self.processes.append(
            spawn(
                "--role",
                "gateway",
                "--endpoint",
                endpoint,
                "--port",
                str(port),
                "--reply-bytes",
                str(self.reply_bytes),
            )
        )
        self.client = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=10)
        deadline = time.monotonic() + 30
        while True:  # until uvicorn listens and the router knows every queryable
            try:
                if self.client.post("/plan", json=self.bodies[0]).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError("the null /plan did not answer within 30 s")
            time.sleep(0.2)
        self.plans(20)  # warm-up

    def __exit__(self, *exc: object) -> None:
        if self.client is not None:
            self.client.close()
        stop(self.processes)

    def plans(self, n: int) -> dict[str, list[float]]:
        """`n` null /plans: per request, seconds beyond the services' sleeps in all (`plan`),
        in the three calls beyond their handlers (`calls`), and the rest (`http`)."""
        assert self.client is not None
        parts: dict[str, list[float]] = {"plan": [], "calls": [], "http": []}
        for i in range(n):
            t0 = time.perf_counter()
            reply = self.client.post("/plan", json=self.bodies[i % len(self.bodies)])
            took_ms = (time.perf_counter() - t0) * 1e3
            assert reply.status_code == 200 and len(reply.content) > self.reply_bytes * 0.9
            timing = server_timing(reply.headers["server-timing"])
            trips = sum(timing[operation] for operation in CALLS)
            handlers = sum(timing[f"{operation}-handler"] for operation in CALLS)
            parts["plan"].append((took_ms - handlers) / 1e3)
            parts["calls"].append((trips - handlers) / 1e3)
            parts["http"].append((took_ms - trips) / 1e3)
        return parts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--role", choices=["echo", "gateway"], help=argparse.SUPPRESS)
    parser.add_argument("--endpoint", help=argparse.SUPPRESS)
    parser.add_argument("--port", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--operation", help=argparse.SUPPRESS)
    parser.add_argument("--sleep-ms", type=float, help=argparse.SUPPRESS)
    parser.add_argument("--reply-bytes", type=int, help=argparse.SUPPRESS)
    parser.add_argument(
        "--handler-ms",
        type=float,
        nargs=3,
        default=[9.0, 1.0, 0.8],
        metavar=("ENCODE", "PATHS", "PROPOSE"),
        help="how long each service sleeps: about the stack's handlers at concurrency 1",
    )
    parser.add_argument("--reply-kb", type=float, default=55.0, help="the reply's size")
    parser.add_argument("--requests", type=int, default=300)
    args = parser.parse_args()
    if args.role == "echo":
        return serve_echo(args.endpoint, args.operation, args.sleep_ms)
    if args.role == "gateway":
        return serve_gateway(args.endpoint, args.port, args.reply_bytes)

    handler_ms = dict(zip(CALLS, args.handler_ms, strict=True))
    with Floor(handler_ms, int(args.reply_kb * 1000)) as floor:
        parts = floor.plans(args.requests)
    for name, seconds in parts.items():
        print(f"{name} (beyond the handlers): {json.dumps(percentiles(seconds))}")
    print(f"transport floor of one /plan, p50: {percentiles(parts['plan'])['p50_ms']:.2f} ms")


if __name__ == "__main__":
    main()
