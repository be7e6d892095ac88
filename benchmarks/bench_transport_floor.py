"""What /plan's transport costs with no work at all: the floor under the stack's overhead.

Times, in separate processes as in the stack:
- service calls through a zenoh router (`lsr router`) to a `Server` whose handler computes
  nothing: the encode call's messages (two 64 px images in, two latents and errors out), and
  small ones (2 KB in) as paths and propose send, each after the 12 ms of idling that a
  service sees between calls at concurrency 1, and back to back;
- an HTTP POST of a real /plan body to a FastAPI route under uvicorn that validates it as
  `PlanRequest` and answers a prebuilt 100 KB body (a plan's PNGs), with httpx as client:
  with a handler that answers at once, and with one that idles as the gateway's does while
  the services work (`--http-idle-ms`; the idle time, as the handler measured it, is taken
  off). Idle client and server threads take longer to wake, as idle services do.

/plan makes three sequential service calls (encode, paths, propose) and one HTTP exchange.
`bench_plan_latency.py` measures this floor beside the stack and the in-process work.

    .venv/bin/python benchmarks/bench_transport_floor.py [--http-idle-ms 15]
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

from plan_requests import percentiles, request_bodies  # noqa: E402

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
ENCODE_IMAGES = (2, 64, 64, 3)  # what the encode call carries
SMALL_IMAGES = (1, 26, 26, 3)  # 2 KB: about what the paths and propose calls carry
IDLE_BETWEEN_CALLS_S = 0.012


def serve_echo(endpoint: str) -> None:
    session = open_session(BusConfig(connect=[endpoint], open_timeout_s=10))
    server = Server(session, "echo", "floor")

    def encode(payload: bytes) -> EncodeReply:
        rows = len(unpack(payload, EncodeRequest).images.numpy())
        return EncodeReply(
            latents=WireArray.of(np.zeros((rows, 64), np.float32)),
            errors=WireArray.of(np.zeros((rows, 2), np.float32)),
        )

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
    def plan(request: PlanRequest, idle_ms: float = 0.0) -> Response:
        started = time.perf_counter()
        if idle_ms > 0:
            time.sleep(idle_ms / 1e3)
        idled = (time.perf_counter() - started) * 1e3
        headers = {"Server-Timing": f"idle;dur={idled:.3f}"}
        return Response(body, media_type="application/json", headers=headers)

    uvicorn.run(app, host="127.0.0.1", port=port, log_level="warning")


def spawn(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, __file__, *args], stdin=subprocess.PIPE, stdout=subprocess.PIPE
    )


class Floor:
    """A router, an echo service and an HTTP echo, each its own process, until closed."""

    def __init__(self) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.http_port = free_port()
        self.router = subprocess.Popen(
            [sys.executable, "-m", "services.cli", "router", "--listen", self.endpoint],
            cwd=ROOT,
            stdout=subprocess.DEVNULL,
        )
        self.echo = spawn("--role", "echo", "--endpoint", self.endpoint)
        self.http_server = spawn("--role", "http", "--port", str(self.http_port))
        self.session = None
        self.client = httpx.Client(base_url=f"http://127.0.0.1:{self.http_port}", timeout=10)
        self.bodies = request_bodies(5, 64, seed=0)

    def __enter__(self) -> Floor:
        assert self.echo.stdout is not None and self.echo.stdout.readline().strip() == b"ready"
        self.session = open_session(BusConfig(connect=[self.endpoint], open_timeout_s=10))
        time.sleep(0.5)  # the router learns the queryable
        deadline = time.monotonic() + 20
        while True:  # until uvicorn listens
            try:
                self.client.post("/plan", json=self.bodies[0])
                break
            except httpx.TransportError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        self.calls(ENCODE_IMAGES, 0.0, 20)  # warm-up
        self.http(0.0, 20)
        return self

    def __exit__(self, *exc: object) -> None:
        self.client.close()
        close_quietly(self.session)
        for process in (self.echo, self.http_server, self.router):
            process.terminate()
            process.wait(10)

    def calls(self, shape: tuple[int, ...], idle_s: float, n: int) -> list[float]:
        """Seconds each of `n` calls took beyond its handler (which the reply reports)."""
        request = EncodeRequest(task="t", images=WireArray.of(np.zeros(shape, np.uint8)))
        beyond = []
        for _ in range(n):
            time.sleep(idle_s)
            pending = call(self.session, "echo", "t", "encode", request, EncodeReply)
            pending.result()
            timing = pending.timing
            beyond.append((timing.round_trip_ms - (timing.handler_ms or 0.0)) / 1e3)
        return beyond

    def http(self, idle_s: float, n: int) -> list[float]:
        """Seconds each of `n` POSTs took beyond the handler's idling."""
        seconds = []
        for i in range(n):
            t0 = time.perf_counter()
            reply = self.client.post(
                "/plan", json=self.bodies[i % len(self.bodies)], params={"idle_ms": idle_s * 1e3}
            )
            took = time.perf_counter() - t0
            assert reply.status_code == 200 and len(reply.content) > REPLY_BYTES * 0.9, reply.text
            idled_ms = float(reply.headers["server-timing"].split("dur=")[1])
            seconds.append(took - idled_ms / 1e3)
        return seconds

    def plan_floor(self, http_idle_s: float, n: int) -> dict[str, float]:
        """p50s (ms) of /plan's parts, and their sum: the floor of one /plan."""
        parts = {
            "encode_call": self.calls(ENCODE_IMAGES, IDLE_BETWEEN_CALLS_S, n),
            "small_call": self.calls(SMALL_IMAGES, IDLE_BETWEEN_CALLS_S, n),
            "http": self.http(http_idle_s, n),
        }
        p50 = {name: float(np.median(s)) * 1e3 for name, s in parts.items()}
        p50["plan"] = p50["encode_call"] + 2 * p50["small_call"] + p50["http"]
        return p50


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--role", choices=["echo", "http"], help=argparse.SUPPRESS)
    parser.add_argument("--endpoint", help=argparse.SUPPRESS)
    parser.add_argument("--port", type=int, help=argparse.SUPPRESS)
    parser.add_argument(
        "--http-idle-ms",
        type=float,
        default=15.0,
        help="how long the HTTP handler idles (about the gateway's time at concurrency 1)",
    )
    args = parser.parse_args()
    if args.role == "echo":
        return serve_echo(args.endpoint)
    if args.role == "http":
        return serve_http(args.port)

    with Floor() as floor:
        idle = IDLE_BETWEEN_CALLS_S
        results = {
            "zenoh_encode_call_after_12_ms_idle": floor.calls(ENCODE_IMAGES, idle, 300),
            "zenoh_small_call_after_12_ms_idle": floor.calls(SMALL_IMAGES, idle, 300),
            "zenoh_encode_call_back_to_back": floor.calls(ENCODE_IMAGES, 0.0, 300),
            "http_post_100kb_out_answered_at_once": floor.http(0.0, 300),
            f"http_post_100kb_out_handler_idle_{args.http_idle_ms:g}_ms": floor.http(
                args.http_idle_ms / 1e3, 300
            ),
        }
    p50 = {}
    for name, seconds in results.items():
        figures = percentiles(seconds[20:])
        p50[name] = figures["p50_ms"]
        print(f"{name} (beyond the handler): {json.dumps(figures)}")
    encode, small, *_, http_at_once, http_idle = p50.values()
    print(
        f"transport floor of one /plan, p50: {encode + 2 * small + http_idle:.2f} ms "
        f"({encode:.2f} + 2 x {small:.2f} + {http_idle:.2f}); with HTTP answered at once "
        f"{encode + 2 * small + http_at_once:.2f} ms"
    )


if __name__ == "__main__":
    main()
