"""Real zenoh sessions on a loopback port: a router and clients, all in this process."""

import socket
import time

import numpy as np
import pytest

from shared.bus import (
    BusConfig,
    RemoteError,
    Server,
    ServiceUnavailable,
    alive_key,
    call,
    close_quietly,
    open_session,
    service_key,
)
from shared.messages import DecodeReply, DecodeRequest, WireArray
from shared.validation import FieldError


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def network():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(BusConfig(mode="router", listen=[endpoint]))
    sessions = [open_session(BusConfig(connect=[endpoint], open_timeout_s=5)) for _ in range(3)]
    yield sessions
    for session in [*sessions, router]:
        close_quietly(session)


def echo_handler(name: str):
    def handle(payload: bytes) -> DecodeReply:
        request = DecodeRequest.model_validate(__import__("msgpack").unpackb(payload))
        z = request.latents.numpy()
        if not np.isfinite(z).all():
            raise FieldError("latents", "contains NaN or infinity")
        images = np.full((len(z), 2, 2, 3), ord(name[0]), np.uint8)
        return DecodeReply(images=WireArray.of(images))

    return handle


def request(z: np.ndarray) -> DecodeRequest:
    return DecodeRequest(task="t", latents=WireArray.of(z.astype(np.float32)))


def test_replicas_on_one_key_share_the_queries_and_errors_name_the_field(network):
    a, b, caller = network
    servers = [Server(a, "decoder", "a"), Server(b, "decoder", "b")]
    for server in servers:
        server.serve(service_key("decoder", "t", "decode"), echo_handler(server.instance))
    time.sleep(0.3)
    answered = set()
    for _ in range(40):
        reply = call(caller, "decoder", "t", "decode", request(np.zeros((1, 2))), DecodeReply)
        images = reply.result().images.numpy()
        assert images.shape == (1, 2, 2, 3)
        answered.add(chr(images[0, 0, 0, 0]))
    assert answered == {"a", "b"}  # both serve, and each query got exactly one answer

    tokens = [r.ok.key_expr for r in caller.liveliness().get("lsr/alive/decoder/*", timeout=2)]
    assert sorted(str(k) for k in tokens) == [alive_key("decoder", "a"), alive_key("decoder", "b")]

    bad = request(np.array([[np.nan, 0.0]]))
    with pytest.raises(RemoteError, match="latents") as info:
        call(caller, "decoder", "t", "decode", bad, DecodeReply).result()
    assert info.value.error.code == "bad_request" and info.value.error.field == "latents"

    servers[0].close()  # one replica leaves: the other takes every query
    time.sleep(0.3)
    for _ in range(5):
        reply = call(caller, "decoder", "t", "decode", request(np.zeros((1, 2))), DecodeReply)
        assert chr(reply.result().images.numpy()[0, 0, 0, 0]) == "b"
    servers[1].close()


def test_a_missing_service_fails_fast_and_by_name(network):
    caller = network[2]
    started = time.monotonic()
    with pytest.raises(ServiceUnavailable, match="nobody service unavailable"):
        call(caller, "nobody", "t", "decode", request(np.zeros((1, 2))), DecodeReply).result()
    assert time.monotonic() - started < 2.0


def test_a_silent_service_times_out_within_the_deadline(network):
    a, _, caller = network
    server = Server(a, "sleepy", "x")
    server.serve(service_key("sleepy", "t", "decode"), lambda _: time.sleep(3) or None)
    time.sleep(0.3)
    started = time.monotonic()
    with pytest.raises(ServiceUnavailable, match="no reply in time"):
        call(
            caller,
            "sleepy",
            "t",
            "decode",
            request(np.zeros((1, 2))),
            DecodeReply,
            deadline_s=1.0,
            attempt_timeout_s=0.5,
        ).result()
    assert time.monotonic() - started < 1.5
    server.close()


def test_opening_without_a_router_gives_up_after_its_timeout():
    config = BusConfig(connect=[f"tcp/127.0.0.1:{free_port()}"], open_timeout_s=0.5)
    with pytest.raises(ConnectionError, match="no zenoh router"):
        open_session(config)
