"""Deadlines over a real router, with services played by the test: a hang costs one budget."""

from __future__ import annotations

import threading
import time

import httpx
import numpy as np
import pytest

from shared.bus import BusConfig, Server, close_quietly, open_session, service_key
from shared.messages import EncodeReply, RenderReply, WireArray

DEADLINE_S = 1.0
STEP_S = 0.3  # what each service before the hanging one takes
STATE = {"stacks": [["red"], ["green", "blue"], ["yellow"]]}
PLAN = {"task": "box_stacking", "start": {"state": STATE}, "goal": {"state": STATE}}


@pytest.fixture(scope="module")
def slow_services(router_endpoint):
    """A sim and an encoder that take STEP_S each, and a planner that hangs."""
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


@pytest.fixture(scope="module")
def gateway_url(gateway_with, slow_services):
    yield from gateway_with(deadline_s=DEADLINE_S)


def test_a_hang_after_slow_steps_gets_503_within_one_request_deadline(gateway_url):
    with httpx.Client(base_url=gateway_url, timeout=10) as http:
        started = time.monotonic()
        reply = http.post("/plan", json=PLAN)
        took = time.monotonic() - started
    assert reply.status_code == 503 and "planner" in reply.json()["detail"], reply.text
    assert reply.headers["retry-after"] == "1"
    # One deadline for the whole request, not one per call after the calls before it.
    assert DEADLINE_S - 0.1 < took < DEADLINE_S + 0.25, took
