"""Slow clients over real sockets: a dribbled body is cut off, and others are served meanwhile."""

from __future__ import annotations

import socket
import threading
import time

import httpx
import pytest

BODY_TIMEOUT_S = 0.5


@pytest.fixture(scope="module")
def strict_gateway(gateway_with):
    yield from gateway_with(body_timeout_s=BODY_TIMEOUT_S)


def dribble(url: str, outcome: list[tuple[bytes, float, bool]]) -> None:
    """POST a 1000-byte body one byte every 50 ms; record the reply, when it ended, and whether
    the server closed the connection (a reset counts: it closed with our bytes unread)."""
    host, port = url.removeprefix("http://").split(":")
    reply = b""
    closed = False
    with socket.create_connection((host, int(port)), timeout=10) as sock:
        started = time.monotonic()
        sock.sendall(
            b"POST /plan HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
            b"Content-Length: 1000\r\n\r\n{"
        )
        sock.settimeout(0.05)
        try:
            for _ in range(200):  # 10 s at most
                sock.sendall(b" ")
                try:
                    chunk = sock.recv(4096)
                except TimeoutError:
                    continue
                if not chunk:
                    closed = True
                    break
                reply += chunk
        except OSError:  # reset or broken pipe: the server closed the connection
            closed = True
        outcome.append((reply, time.monotonic() - started, closed))


def test_dribbled_bodies_get_408_and_their_connections_close(strict_gateway):
    outcome: list[tuple[bytes, float, bool]] = []
    clients = [threading.Thread(target=dribble, args=(strict_gateway, outcome)) for _ in range(20)]
    for client in clients:
        client.start()
    time.sleep(0.1)
    with httpx.Client(base_url=strict_gateway, timeout=5) as http:
        started = time.monotonic()
        assert http.get("/tasks/box_stacking").status_code == 200  # served meanwhile
        assert time.monotonic() - started < 0.5
    for client in clients:
        client.join(15)
    assert len(outcome) == 20
    for reply, took, closed in outcome:
        assert closed and BODY_TIMEOUT_S - 0.1 < took < BODY_TIMEOUT_S + 1.5, (took, reply[:300])
        assert reply == b"" or reply.startswith(b"HTTP/1.1 408"), reply[:100]
    assert any(reply.startswith(b"HTTP/1.1 408") for reply, _, _ in outcome)  # not all reset


def test_a_body_sent_at_once_is_not_affected(strict_gateway):
    with httpx.Client(base_url=strict_gateway, timeout=5) as http:
        reply = http.post("/plan", json={"task": "box_stacking"})
    assert reply.status_code == 422  # validated as usual: start and goal are missing
