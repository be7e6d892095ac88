"""Real zenoh sessions on a loopback port: a router and clients, all in this process."""

import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import msgpack
import numpy as np
import pytest

from services.stack import free_port
from shared.bus import (
    MSGPACK,
    Backlog,
    Batched,
    BusConfig,
    RemoteError,
    Replicas,
    Server,
    ServiceUnavailable,
    alive_key,
    call,
    close_quietly,
    open_session,
    service_key,
)
from shared.deadlines import DeadlineExceeded, check_deadline, working_until
from shared.messages import DecodeReply, DecodeRequest, ErrorReply, WireArray, unpack
from shared.validation import FieldError, check_latents


@pytest.fixture(scope="module")
def endpoint():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(BusConfig(mode="router", listen=[endpoint]))
    yield endpoint
    close_quietly(router)


@pytest.fixture(scope="module")
def network(endpoint):
    sessions = [open_session(BusConfig(connect=[endpoint], open_timeout_s=5)) for _ in range(3)]
    yield sessions
    for session in sessions:
        close_quietly(session)


def echo_handler(name: str, calls: list[str]):
    def handle(payload: bytes) -> DecodeReply:
        calls.append(name)
        z = unpack(payload, DecodeRequest).latents.numpy()
        if not np.isfinite(z).all():
            raise FieldError("latents", "contains NaN or infinity")
        return DecodeReply(images=WireArray.of(np.full((len(z), 2, 2, 3), ord(name), np.uint8)))

    return handle


def request(z: np.ndarray) -> DecodeRequest:
    return DecodeRequest(task="t", latents=WireArray.of(z.astype(np.float32)))


def test_replicas_share_the_queries_one_answer_each_and_errors_name_the_field(network):
    a, b, caller = network
    calls: list[str] = []
    servers = [Server(a, "decoder", "a"), Server(b, "decoder", "b")]
    for server in servers:
        server.serve(service_key("decoder", "t", "decode"), echo_handler(server.instance, calls))
    replicas = Replicas(caller)
    time.sleep(0.3)

    def decode(z: np.ndarray, picker: Replicas | None = replicas) -> str:
        reply = call(caller, "decoder", "t", "decode", request(z), DecodeReply, replicas=picker)
        return chr(reply.result().images.numpy()[0, 0, 0, 0])

    answered = [decode(np.zeros((1, 2))) for _ in range(40)]
    assert sorted(calls) == sorted(answered)  # every query was computed exactly once
    assert answered.count("a") == answered.count("b") == 20  # and the replicas took turns
    calls.clear()
    assert decode(np.zeros((1, 2)), picker=None) in "ab" and len(calls) == 1  # the shared key

    tokens = [r.ok.key_expr for r in caller.liveliness().get("lsr/alive/decoder/*", timeout=2)]
    assert sorted(str(k) for k in tokens) == [alive_key("decoder", "a"), alive_key("decoder", "b")]

    with pytest.raises(RemoteError, match="latents") as info:
        decode(np.array([[np.nan, 0.0]]))
    assert info.value.error.code == "bad_request" and info.value.error.field == "latents"

    servers[0].close()  # one replica leaves: the other takes every query at once
    assert [decode(np.zeros((1, 2))) for _ in range(6)] == ["b"] * 6
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
    late = DecodeReply(images=WireArray.of(np.zeros((1, 2, 2, 3), np.uint8)))
    server.serve(service_key("sleepy", "t", "decode"), lambda _: time.sleep(3) or late)
    time.sleep(0.3)
    started = time.monotonic()
    with pytest.raises(ServiceUnavailable, match="no reply in time"):
        pending = call(caller, "sleepy", "t", "decode", request(np.zeros((1, 2))), DecodeReply, 1.0)
        pending.result()
    assert time.monotonic() - started < 1.5
    server.close()


def test_queries_whose_caller_gave_up_are_dropped_not_computed(network):
    a, _, caller = network
    server = Server(a, "slow", "x")
    computed: list[float] = []

    def slow(_: bytes) -> DecodeReply:
        computed.append(time.monotonic())
        time.sleep(0.4)
        return DecodeReply(images=WireArray.of(np.zeros((1, 2, 2, 3), np.uint8)))

    server.serve(service_key("slow", "t", "decode"), slow)
    time.sleep(0.3)
    z = request(np.zeros((1, 2)))
    waiting = [call(caller, "slow", "t", "decode", z, DecodeReply, 0.3) for _ in range(5)]
    for pending in waiting:
        with pytest.raises(ServiceUnavailable):
            pending.result()
    time.sleep(0.6)  # the first query's work ends; the other four waited past their budget
    assert len(computed) == 1 and server.expired == 4
    assert call(caller, "slow", "t", "decode", z, DecodeReply, 2.0).result()  # serves again
    server.close()


def test_work_past_its_callers_deadline_is_abandoned_between_steps(network):
    """A handler that checks the deadline (physics between steps) stops once its caller has
    stopped waiting: the query behind it is served in time, and the 503 names the operation."""
    a, _, caller = network
    server = Server(a, "stepper", "x")
    steps: list[int] = []

    def long_work(payload: bytes) -> DecodeReply:
        for step in range(100):  # 5 s of work, unless abandoned
            time.sleep(0.05)
            steps.append(step)
            check_deadline()
        return DecodeReply(images=WireArray.of(np.zeros((1, 2, 2, 3), np.uint8)))

    server.serve(service_key("stepper", "t", "fold"), long_work)
    time.sleep(0.3)
    z = request(np.zeros((1, 2)))
    with pytest.raises(ServiceUnavailable, match=r"no reply in time on .*/fold: fold ran out of"):
        call(caller, "stepper", "t", "fold", z, DecodeReply, 0.5).result()
    started = time.monotonic()
    with pytest.raises(ServiceUnavailable):  # waits behind the first only until it is abandoned
        call(caller, "stepper", "t", "fold", z, DecodeReply, 0.8).result()
    time.sleep(0.3)
    assert len(steps) < 40  # both stopped near their deadlines, not after 100 steps each
    assert server.expired == 2 and time.monotonic() - started < 1.5
    server.close()


def test_deadlines_are_per_thread_and_none_outside_a_request():
    check_deadline()  # no request: nothing to check
    with working_until(time.monotonic() - 1):
        with pytest.raises(DeadlineExceeded, match="deadline passed"):
            check_deadline()
        with working_until(None):
            check_deadline()
    check_deadline()


def test_queued_queries_are_answered_in_batches_each_with_its_own_reply(network):
    a, _, caller = network
    server = Server(a, "batcher", "x")
    batches: list[int] = []

    def parse(payload: bytes) -> np.ndarray:
        z = unpack(payload, DecodeRequest).latents.numpy()
        if not np.isfinite(z).all():
            raise FieldError("latents", "contains NaN or infinity")
        return z

    def run(requests: list[np.ndarray]) -> list[DecodeReply]:
        batches.append(len(requests))
        time.sleep(0.2)  # the others queue up meanwhile
        value = [np.full((1, 1, 1, 3), z[0, 0], np.uint8) for z in requests]
        return [DecodeReply(images=WireArray.of(v)) for v in value]

    server.serve(service_key("batcher", "t", "decode"), Batched(parse, run, max_batch=8))
    time.sleep(0.3)
    values = [np.full((1, 2), v) for v in range(6)]
    values.insert(3, np.array([[np.nan, 0.0]]))  # one bad request among them
    waiting = [call(caller, "batcher", "t", "decode", request(z), DecodeReply, 3.0) for z in values]
    answers = []
    for pending in waiting:
        try:
            answers.append(int(pending.result().images.numpy()[0, 0, 0, 0]))
        except RemoteError as exc:
            answers.append(exc.error.field)
    assert answers == [0, 1, 2, "latents", 3, 4, 5]  # each query got its own answer
    assert sum(batches) == 6 and len(batches) < 6  # computed together, the bad one not at all
    server.close()


@pytest.mark.parametrize(
    "run",
    [lambda requests: 1 / 0, lambda requests: []],
    ids=["run raises", "run returns too few replies"],
)
def test_a_failing_batch_answers_each_query_with_an_internal_error(network, run):
    a, _, caller = network
    server = Server(a, "broken", "x")
    server.serve(service_key("broken", "t", "decode"), Batched(lambda payload: payload, run))
    time.sleep(0.3)
    started = time.monotonic()
    waiting = [
        call(caller, "broken", "t", "decode", request(np.zeros((1, 2))), DecodeReply, 2.0)
        for _ in range(3)
    ]
    for pending in waiting:
        with pytest.raises(RemoteError) as info:
            pending.result()
        assert info.value.error.code == "internal"
    assert time.monotonic() - started < 1.0  # answered, not left to time out
    server.close()


def test_opening_without_a_router_gives_up_after_its_timeout():
    config = BusConfig(connect=[f"tcp/127.0.0.1:{free_port()}"], open_timeout_s=0.5)
    with pytest.raises(ConnectionError, match="no zenoh router"):
        open_session(config)


def latents_handler(payload: bytes) -> DecodeReply:
    z = check_latents("latents", unpack(payload, DecodeRequest).latents, 2, max_rows=8)
    return DecodeReply(images=WireArray.of(np.zeros((len(z), 1, 1, 3), np.uint8)))


def raw_latents(shape: list[int], data: bytes = b"") -> bytes:
    array = {"shape": shape, "dtype": "<f4", "data": data}
    return msgpack.packb({"v": 1, "task": "t", "latents": array})


@pytest.mark.parametrize(
    ("payload", "field"),
    [
        (raw_latents([0, 2**64 - 1]), "latents.shape.1"),
        (raw_latents([2**62, 2**62, 0]), "latents.shape.0"),
        (raw_latents([2**30, 2**30, 0]), "latents"),
        (raw_latents([0, 2]), "latents"),  # empty: no rows to decode
        (raw_latents([1, 2], b"12"), "latents"),  # byte count against shape
        (b"\xc1 not msgpack", None),
    ],
    ids=["2**64-1", "2**62 x 2**62 x 0", "2**60 elements", "no rows", "short data", "not msgpack"],
)
def test_bad_arrays_get_bad_request_by_field_and_the_query_ends_at_once(network, payload, field):
    a, _, caller = network
    server = Server(a, "strict", "x")
    server.serve(service_key("strict", "t", "decode"), latents_handler)
    time.sleep(0.3)
    started = time.monotonic()
    replies = list(
        caller.get(
            service_key("strict", "t", "decode"), payload=payload, encoding=MSGPACK, timeout=5
        )
    )
    took = time.monotonic() - started  # until the query was finalized, not its first reply
    server.close()
    assert len(replies) == 1 and replies[0].err is not None
    error = unpack(replies[0].err.payload.to_bytes(), ErrorReply)
    assert error.code == "bad_request", error
    assert (error.field or "").startswith(field) if field else error.field is None
    assert took < 1.0, took  # closed after the reply, not left to the caller's timeout


def start_replica(endpoint: str, instance: str) -> subprocess.Popen:
    script = Path(__file__).with_name("replica_process.py")
    process = subprocess.Popen(
        [sys.executable, str(script), endpoint, instance], stdout=subprocess.PIPE, text=True
    )
    assert process.stdout is not None and process.stdout.readline().strip() == "ready"
    return process


def live(replicas: Replicas, service: str, count: int) -> None:
    deadline = time.monotonic() + 5
    while len(replicas._alive.get(service, [])) != count:
        assert time.monotonic() < deadline, replicas._alive
        time.sleep(0.02)


@pytest.mark.parametrize("stall_s", [0.3, 0.0], ids=["stalled then killed", "killed"])
def test_queries_held_by_a_replica_that_dies_are_answered_by_a_live_one(endpoint, network, stall_s):
    a, _, caller = network
    server = Server(a, "decoder", "b")  # the replica that lives, in this process
    server.serve(service_key("decoder", "t", "decode"), echo_handler("b", []))
    doomed = start_replica(endpoint, "dying")
    replicas = Replicas(caller)
    try:
        live(replicas, "decoder", 2)

        def decode(_: int) -> str:
            pending = call(
                caller,
                "decoder",
                "t",
                "decode",
                request(np.zeros((1, 2))),
                DecodeReply,
                deadline_s=3.0,
                replicas=replicas,
            )
            return chr(pending.result().images.numpy()[0, 0, 0, 0])

        with ThreadPoolExecutor(8) as pool:
            if stall_s:
                doomed.send_signal(signal.SIGSTOP)  # queries sent to it now stay with it
            answers = pool.map(decode, range(80))
            time.sleep(stall_s or 0.05)
            doomed.kill()
            answered = list(answers)  # raises if any query failed
        assert len(answered) == 80 and set(answered) <= {"d", "b"}
        assert "b" in answered
    finally:
        doomed.kill()
        doomed.wait(10)
        server.close()


def test_a_backlog_holds_up_to_its_cost_and_always_one_query():
    backlog = Backlog(16.0)
    assert backlog.admit(25.0)  # alone, however costly: a queue never refuses everything
    assert not backlog.admit(0.3)
    backlog.done(25.0)
    assert backlog.admit(10.0) and backlog.admit(6.0) and not backlog.admit(0.5)
    backlog.done(10.0)
    assert backlog.admit(0.5)
    assert all(Backlog(None).admit(1e9) for _ in range(3))  # unbounded
