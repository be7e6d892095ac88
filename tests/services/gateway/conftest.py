"""A real gateway (uvicorn on a loopback port) joined to a real zenoh router, no services.

Enough for everything the gateway judges itself: bodies, validation, limits, deadlines of calls
to services that are absent or played by the test.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import httpx
import numpy as np
import pytest
import uvicorn

from services.gateway.app import create_app
from services.stack import free_port
from shared.bus import BusConfig, Server, close_quietly, open_session, service_key
from shared.messages import EncodeReply, RenderReply, WireArray
from shared.settings import Settings


@dataclass
class LiveGateway:
    url: str
    endpoint: str  # the router's
    settings: Settings


@pytest.fixture(scope="module")
def router_endpoint() -> Iterator[str]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(BusConfig(mode="router", listen=[endpoint]))
    yield endpoint
    close_quietly(router)


def serve(settings: Settings) -> Iterator[str]:
    """Run the gateway app in a thread until the generator is closed; yields its URL."""
    server = uvicorn.Server(
        uvicorn.Config(
            create_app(settings), host="127.0.0.1", port=settings.port, log_level="warning"
        )
    )
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 20
    while not server.started:
        assert time.monotonic() < deadline and thread.is_alive(), "gateway did not start"
        time.sleep(0.05)
    yield f"http://127.0.0.1:{settings.port}"
    server.should_exit = True
    thread.join(10)


@pytest.fixture(scope="module")
def gateway_with(router_endpoint: str) -> Callable[..., Iterator[str]]:
    """`yield from gateway_with(**settings)` in a fixture: a gateway of those settings."""

    def start(**overrides: Any) -> Iterator[str]:
        settings = Settings(zenoh_connect=router_endpoint, port=free_port(), **overrides)
        yield from serve(settings)

    return start


@pytest.fixture(scope="module")
def live_gateway(router_endpoint: str) -> Iterator[LiveGateway]:
    settings = Settings(zenoh_connect=router_endpoint, port=free_port(), deadline_s=1.0)
    for url in serve(settings):
        yield LiveGateway(url, router_endpoint, settings)


@pytest.fixture(scope="module")
def http(live_gateway: LiveGateway) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=live_gateway.url, timeout=30) as client:
        yield client


@pytest.fixture(scope="session")
def wide_body() -> bytes:
    """A JSON object of 340,000 distinct short keys: about 3 MB, under the body limit."""
    digits = "0123456789abcdefghijklmnopqrstuvwxyz"

    def name(i: int) -> str:
        out = ""
        while True:
            i, r = divmod(i, 36)
            out = digits[r] + out
            if not i:
                return out

    return json.dumps({name(i): 1 for i in range(340_000)}, separators=(",", ":")).encode()


STEP_S = 0.3  # what each slow service before the hanging planner takes


@pytest.fixture(scope="module")
def slow_services(router_endpoint):
    """A sim and an encoder that take STEP_S each, and a planner that hangs (8 s at most)."""
    session = open_session(BusConfig(connect=[router_endpoint], open_timeout_s=5))
    release = threading.Event()

    def render(_: bytes) -> RenderReply:
        time.sleep(STEP_S)
        return RenderReply(images=WireArray.of(np.zeros((2, 8, 8, 3), np.uint8)))

    def encode(_: bytes) -> EncodeReply:
        time.sleep(STEP_S)
        return EncodeReply(latents=WireArray.of(np.zeros((2, 4), np.float32)))

    def paths(_: bytes) -> EncodeReply:
        release.wait(8)  # a planner hang
        raise RuntimeError("hung")

    servers = []
    for service, operation, handler in [
        ("sim", "render", render),
        ("encoder", "encode", encode),
        ("planner", "paths", paths),
    ]:
        server = Server(session, service, f"{service}-stub")
        server.serve(service_key(service, "box_stacking", operation), handler)
        servers.append(server)
    time.sleep(0.3)
    yield
    release.set()
    for server in servers:
        server.close()
    close_quietly(session)
