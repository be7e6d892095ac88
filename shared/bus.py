"""Zenoh plumbing every process shares: sessions, key names, typed queries with deadlines.

Key layout (documented in docs/services.md):
  lsr/{service}/{task}/{operation}   queryables of the services (msgpack messages)
  lsr/alive/{service}/{instance}     liveliness tokens
  lsr/api/plan                       the public planning queryable (JSON, served by the gateway)
  lsr/robot/{robot_id}/plan          plans published for robots (JSON)
  lsr/sim/{task}/progress/{run_id}   steps of a running episode, published by the sim (msgpack)
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import queue
import signal
import socket
import threading
import time
import traceback
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Generic, TypeVar

import zenoh
from pydantic import BaseModel

from shared.deadlines import DeadlineExceeded, working_until
from shared.messages import (
    CallBudget,
    ErrorReply,
    InfoReply,
    M,
    MessageError,
    ReplyMeta,
    pack,
    unpack,
)
from shared.tasks.base import TaskError
from shared.validation import FieldError

log = logging.getLogger(__name__)

MSGPACK = zenoh.Encoding("application/msgpack")
JSON = zenoh.Encoding.APPLICATION_JSON
DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
SERVICES = ("encoder", "planner", "apn", "sim")
UNSERVED_GRACE_S = 0.5


def service_key(service: str, task: str, operation: str) -> str:
    return f"lsr/{service}/{task}/{operation}"


def alive_key(service: str, instance: str) -> str:
    return f"lsr/alive/{service}/{instance}"


# A robot id is one key chunk: none of zenoh's special characters / * $ ? #, no control characters,
# and no leading @ (zenoh's verbatim chunks, which wildcards do not match).
ROBOT_ID_PATTERN = r"^[^@/*$?#\x00-\x1f\x7f][^/*$?#\x00-\x1f\x7f]{0,127}$"


def robot_plan_key(robot_id: str) -> str:
    return f"lsr/robot/{robot_id}/plan"


API_PLAN_KEY = "lsr/api/plan"
EXPERIENCE_KEYS = "lsr/experience/*"


def experience_key(task: str) -> str:
    """Where robots report what they did (`POST /experience` over zenoh); the gateway records."""
    return f"lsr/experience/{task}"


def progress_key(task: str, run_id: str) -> str:
    """Where the sim publishes the steps of a running episode (`RunRequest.progress`)."""
    return f"lsr/sim/{task}/progress/{run_id}"


def host_id() -> str:
    """The hostname, made safe for a key chunk."""
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in socket.gethostname())


def new_instance_id() -> str:
    """hostname-pid-random: unique per process, and says where it runs."""
    return f"{host_id()}-{os.getpid()}-{uuid.uuid4().hex[:6]}"


@dataclass
class BusConfig:
    """How a process joins the zenoh network: a client of routers, or the router itself."""

    connect: Sequence[str] | None = None  # None: a client's DEFAULT_ENDPOINT, a router's none
    mode: str = "client"
    listen: Sequence[str] = ()
    open_timeout_s: float | None = None  # None: keep retrying until a router answers
    # A zenoh configuration file loaded first (LSR_ZENOH_CONFIG): credentials, TLS and, for
    # the router, access control (`shared.zenoh_access`). The fields above are set on top.
    config_file: Path | None = None

    @property
    def endpoints(self) -> list[str]:
        """The endpoints it connects to: routers for a client, other routers for a router."""
        if self.connect is None:
            return [] if self.mode == "router" else [DEFAULT_ENDPOINT]
        return list(self.connect)

    def zenoh_config(self) -> zenoh.Config:
        config = (
            zenoh.Config.from_file(str(self.config_file)) if self.config_file else zenoh.Config()
        )
        config.insert_json5("mode", json.dumps(self.mode))
        config.insert_json5("scouting/multicast/enabled", "false")
        connect = self.endpoints
        if connect:
            config.insert_json5("connect/endpoints", json.dumps(connect))
        if self.listen:
            config.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        return config


def open_session(config: BusConfig) -> zenoh.Session:
    """Open a session, retrying while no router is reachable (containers start in any order)."""
    deadline = None if config.open_timeout_s is None else time.monotonic() + config.open_timeout_s
    delay = 0.2
    while True:
        try:
            return zenoh.open(config.zenoh_config())
        except zenoh.ZError as exc:
            if deadline is not None and time.monotonic() + delay > deadline:
                raise ConnectionError(f"no zenoh router at {config.endpoints}: {exc}") from None
            log.warning("zenoh router at %s not reachable yet; retrying", config.endpoints)
            time.sleep(delay)
            delay = min(delay * 2, 2.0)


def close_quietly(session: zenoh.Session, timeout_s: float = 3.0) -> None:
    """Close a session, but never hang a shutdown on it."""
    closer = threading.Thread(target=session.close, daemon=True)
    closer.start()
    closer.join(timeout_s)


def wait_for_stop_signal() -> None:
    """Block until SIGINT or SIGTERM: a long-running process's main thread."""
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    while not stop.wait(0.5):
        pass


class ServiceUnavailable(RuntimeError):
    """No instance of a service answered in time."""

    def __init__(self, service: str, reason: str) -> None:
        super().__init__(f"{service} service unavailable: {reason}")
        self.service = service
        self.reason = reason


class RemoteError(RuntimeError):
    """A service answered with an error (bad_request: the caller's fault; internal: its own)."""

    def __init__(self, service: str, error: ErrorReply) -> None:
        where = f" ({error.field})" if error.field else ""
        super().__init__(f"{service}: {error.message}{where}")
        self.service = service
        self.error = error


class Replicas:
    """The live instances of every service, from their liveliness tokens, taken in turn.

    Zenoh sends a query to every matching queryable unless one is declared complete, and then
    always to the same one; so callers spread queries themselves, over per-instance keys.
    """

    def __init__(self, session: zenoh.Session) -> None:
        self._alive: dict[str, list[str]] = {}
        self._turn: dict[str, int] = {}
        self._lock = threading.Lock()
        self._subscriber = session.liveliness().declare_subscriber(
            "lsr/alive/*/*", self._on_token, history=True
        )

    def _on_token(self, sample: zenoh.Sample) -> None:
        _, _, service, instance = str(sample.key_expr).split("/")
        with self._lock:
            alive = self._alive.setdefault(service, [])
            if sample.kind == zenoh.SampleKind.PUT and instance not in alive:
                alive.append(instance)
            elif sample.kind == zenoh.SampleKind.DELETE and instance in alive:
                alive.remove(instance)

    def pick(self, service: str) -> str | None:
        with self._lock:
            alive = self._alive.get(service)
            if not alive:
                return None
            turn = self._turn.get(service, 0)
            self._turn[service] = turn + 1
            return alive[turn % len(alive)]

    def forget(self, service: str, instance: str) -> None:
        with self._lock:
            if instance in self._alive.get(service, []):
                self._alive[service].remove(instance)


@dataclass(frozen=True)
class CallTiming:
    operation: str
    round_trip_ms: float  # as the caller saw it
    handler_ms: float | None  # inside the service, as its reply says


@dataclass
class PendingCall:
    """A query on its way; `result()` waits for the reply. Lets callers run queries in parallel.

    The query goes to one instance: the next live one by `replicas`, or, before any is known, to
    the shared key (where every instance is a complete queryable, so zenoh picks one). A query
    that ends unanswered before its deadline (nobody serves it, or the instance that held it
    died) is sent again, to another live instance, for up to UNSERVED_GRACE_S. A query that is
    still held when the deadline comes is not repeated: the work would only pile up on a slow
    instance.
    """

    session: zenoh.Session
    key: str
    service: str
    payload: bytes
    reply_type: type[BaseModel]
    deadline: float
    replicas: Replicas | None = None
    instance: str | None = field(init=False, default=None)
    replies: object = field(init=False)
    sent_at: float = field(init=False, default=0.0)
    round_trip_ms: float | None = field(init=False, default=None)  # of the answered query
    served: ReplyMeta | None = field(init=False, default=None)  # the answer's attachment
    budget_s: float = field(init=False, default=0.0)  # the whole call's, retries included

    def __post_init__(self) -> None:
        self.budget_s = self.deadline - time.monotonic()
        self._send()

    def _send(self) -> None:
        self.instance = self.replicas.pick(self.service) if self.replicas else None
        budget_s = max(0.05, self.deadline - time.monotonic())
        self.sent_at = time.perf_counter()
        self.replies = self.session.get(
            f"{self.key}/{self.instance}" if self.instance else self.key,
            payload=self.payload,
            encoding=MSGPACK,
            attachment=pack(CallBudget(budget_ms=int(budget_s * 1e3))),
            target=zenoh.QueryTarget.BEST_MATCHING,
            congestion_control=zenoh.CongestionControl.BLOCK,
            express=True,  # sent at once, not batched: each call is on a request's critical path
            timeout=budget_s,
        )

    @property
    def timing(self) -> CallTiming | None:
        """How long the answered query took, and its handler; None before an answer."""
        if self.round_trip_ms is None:
            return None
        handler_ms = None if self.served is None else self.served.handler_ms
        return CallTiming(self.key.rsplit("/", 1)[-1], self.round_trip_ms, handler_ms)

    def result(self) -> BaseModel:
        unserved_since: float | None = None
        while True:
            timed_out = False
            for reply in self.replies:  # type: ignore[attr-defined]
                if reply.ok is not None:
                    self.round_trip_ms = (time.perf_counter() - self.sent_at) * 1e3
                    self.served = _meta(reply.ok.attachment)
                    return _decode(self.service, reply.ok.payload.to_bytes(), self.reply_type)
                if reply.err.encoding != MSGPACK:  # zenoh's own "Timeout": no answer came
                    timed_out = True
                    continue
                error: ErrorReply = _decode(self.service, reply.err.payload.to_bytes(), ErrorReply)
                if error.code == "unavailable":  # a service this one depends on is down
                    raise ServiceUnavailable(error.field or self.service, error.message)
                raise RemoteError(self.service, error)
            now = time.monotonic()
            if timed_out or now >= self.deadline:  # served, but silent until the deadline
                operation = self.key.rsplit("/", 1)[-1]
                raise ServiceUnavailable(
                    self.service,
                    f"no reply in time on {self.key}: {operation} ran out of its "
                    f"{self.budget_s:.1f} s",
                )
            # Ended unanswered before the deadline: nobody served the query, or the instance
            # that had it is gone (killed, or stalled and then dead) before its token. The work
            # was lost with it, so sending it to another instance repeats nothing.
            if self.instance is not None and self.replicas is not None:
                self.replicas.forget(self.service, self.instance)
            unserved_since = unserved_since or now
            if now - unserved_since > UNSERVED_GRACE_S:
                raise ServiceUnavailable(self.service, f"no instance serves {self.key}")
            time.sleep(0.02)
            self._send()


def _meta(attachment: zenoh.ZBytes | None) -> ReplyMeta | None:
    try:
        return None if attachment is None else unpack(attachment.to_bytes(), ReplyMeta)
    except MessageError:
        return None


def _decode(service: str, payload: bytes, kind: type[M]) -> M:
    try:
        return unpack(payload, kind)
    except MessageError as exc:
        raise RemoteError(
            service, ErrorReply(code="internal", message=f"unreadable reply: {exc}")
        ) from None


def call(
    session: zenoh.Session,
    service: str,
    task: str,
    operation: str,
    request: BaseModel,
    reply_type: type[M],
    deadline_s: float = 4.5,
    replicas: Replicas | None = None,
) -> PendingCall:
    """Send a typed query to one instance of `service`; `.result()` returns a `reply_type`."""
    return PendingCall(
        session,
        service_key(service, task, operation),
        service,
        pack(request),
        reply_type,
        time.monotonic() + deadline_s,
        replicas,
    )


def instances(
    session: zenoh.Session, service: str, task: str, instance: str = "*", timeout_s: float = 1.5
) -> Callable[[], list[InfoReply]]:
    """Ask every live instance (or those matching `instance`) for its info; call to collect."""
    replies = session.get(
        service_key(service, task, f"info/{instance}"),
        target=zenoh.QueryTarget.ALL,
        consolidation=zenoh.ConsolidationMode.NONE,
        timeout=timeout_s,
    )

    def collect() -> list[InfoReply]:
        found = []
        for reply in replies:
            if reply.ok is not None:
                try:
                    found.append(unpack(reply.ok.payload.to_bytes(), InfoReply))
                except MessageError:
                    continue
        return sorted(found, key=lambda info: info.instance)

    return collect


def encoder_image_size(session: zenoh.Session, task: str, timeout_s: float = 1.5) -> int:
    """The image size of the model the encoders of `task` serve, asked of them."""
    found = instances(session, "encoder", task, timeout_s=timeout_s)()
    if not found:
        raise ServiceUnavailable("encoder", f"no instance serves task {task!r}")
    return found[0].image_size


Handler = Callable[[bytes], BaseModel]
Pending = queue.Queue[tuple[float, zenoh.Query, float] | None]  # arrived, query, its cost


class Backlog:
    """What one operation's queue holds, in the cost of its queries (`Batched.cost`), against
    its bound (`Batched.max_queued`; None: none). A query is let in while the queue holds
    less than the bound with it, or when the queue is empty (however costly it is alone)."""

    def __init__(self, limit: float | None) -> None:
        self.limit = limit
        self.cost = 0.0
        self._lock = threading.Lock()

    def admit(self, cost: float) -> bool:
        with self._lock:
            if self.limit is not None and self.cost > 0 and self.cost + cost > self.limit:
                return False
            self.cost += cost
            return True

    def done(self, cost: float) -> None:
        with self._lock:
            self.cost = max(0.0, self.cost - cost)


R = TypeVar("R")


def lower_priority(nice: int) -> None:
    """The calling thread's niceness (Linux): heavy work yields the CPU to light work."""
    if nice:
        with contextlib.suppress(AttributeError, OSError):  # not Linux: as it is
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)


@dataclass(frozen=True)
class Batched(Generic[R]):
    """An operation that answers every query queued at once with one computation (a forward
    pass over all their images, say): under load it costs much less per query than one by one.

    `parse` turns one payload into its request, raising for bad input (that query alone gets
    the error); `run` turns the requests of a batch into their replies, in order.
    `max_queued`: a query that would take the queries waiting beyond this cost is answered
    "unavailable" at once (the gateway's 503 with Retry-After), so that heavy work neither
    piles up nor holds its callers until their deadline; `cost` prices a payload (from its
    header: pixels, say; unset: each query costs 1).
    """

    parse: Callable[[bytes], R]
    run: Callable[[list[R]], list[BaseModel]]
    max_batch: int = 8
    max_queued: float | None = None
    nice: int = 0  # its worker thread's niceness (Linux): heavy work yields the CPU to light
    cost: Callable[[bytes], float] | None = None


Operation = Handler | Batched  # what a service answers one of its keys with


def budget_s(query: zenoh.Query) -> float:
    """How long the caller waits for this query; without a readable budget, for ever."""
    if query.attachment is None:
        return float("inf")
    try:
        return unpack(query.attachment.to_bytes(), CallBudget).budget_ms / 1e3
    except MessageError:
        return float("inf")


class Server:
    """Declares queryables for one service instance, each served by its own worker thread.

    Handlers raise MessageError, FieldError or TaskError for a bad request; anything else is
    internal. A plain handler is a batch of one whose `parse` does all the work.
    Work happens off zenoh's callback threads, so a slow handler never stalls the network. A query
    still queued when its caller's budget (`CallBudget`) has run out is dropped unanswered: under
    overload the queue drains instead of computing replies nobody waits for. Work that checks
    `shared.deadlines.check_deadline` (physics loops) is abandoned the same way once it runs past
    that budget, so a slow request never makes the ones behind it late.
    """

    def __init__(self, session: zenoh.Session, service: str, instance: str) -> None:
        self.session = session
        self.service = service
        self.instance = instance
        self.token = session.liveliness().declare_token(alive_key(service, instance))
        self._queryables: list[zenoh.Queryable] = []
        self._queues: list[Pending] = []
        self.expired = 0  # queries dropped because their caller had stopped waiting
        self._expired_lock = threading.Lock()

    def serve(self, key: str, handler: Operation, per_instance: bool = True) -> None:
        """Answer `key` (as a complete queryable) and, for callers that pick, `key/instance`."""
        work = handler if isinstance(handler, Batched) else Batched(handler, list, max_batch=1)
        pending: Pending = queue.Queue()
        backlog = Backlog(work.max_queued)
        operation = key.rsplit("/", 1)[-1]

        def arrived(query: zenoh.Query) -> None:
            cost = 1.0
            if work.cost is not None:
                with contextlib.suppress(Exception):  # unreadable: its parse will say why
                    cost = work.cost(query.payload.to_bytes() if query.payload else b"")
            if not backlog.admit(cost):
                busy = ErrorReply(
                    code="unavailable",
                    field=self.service,
                    message=f"{self.service} is busy: its {operation} queue is full; try again "
                    "in a second",
                )
                try:
                    query.reply_err(pack(busy), encoding=MSGPACK)
                finally:
                    finish([query])
                return
            pending.put((time.monotonic(), query, cost))

        keys = [key, f"{key}/{self.instance}"] if per_instance else [key]
        for k in keys:
            self._queryables.append(self.session.declare_queryable(k, arrived, complete=True))
        self._queues.append(pending)
        thread = threading.Thread(
            target=self._loop, args=(pending, work, backlog), name=key, daemon=True
        )
        thread.start()

    def _loop(self, pending: Pending, work: Batched, backlog: Backlog) -> None:
        lower_priority(work.nice)
        while (batch := self._next_batch(pending, work.max_batch, backlog)) is not None:
            queries = [query for _, query in batch]
            try:
                # The batch works until the latest of its callers stops waiting: long work
                # (physics, say) checks it between steps and gives up (DeadlineExceeded).
                with working_until(max(arrived + budget_s(q) for arrived, q in batch)):
                    self._answer(queries, work)
            except DeadlineExceeded:
                self._expire(queries, "abandoned in the work")
            except Exception:  # a reply that could not be sent must not end the worker
                log.exception("%s could not answer a query", self.service)
            finally:
                finish(queries)

    def _next_batch(
        self, pending: Pending, max_batch: int, backlog: Backlog
    ) -> list[tuple[float, zenoh.Query]] | None:
        """The oldest query and those queued behind it (with their arrival times), expired
        ones dropped; None: stop. Taken off the queue, they leave its backlog."""
        items = [pending.get()]
        while items[-1] is not None and len(items) < max_batch:
            try:
                items.append(pending.get_nowait())
            except queue.Empty:
                break
        if items[-1] is None:  # stop, once the queries before it are answered
            items.pop()
            if not items:
                return None
            pending.put(None)
        live = []
        for arrived, query, cost in items:  # type: ignore[misc]
            backlog.done(cost)
            if time.monotonic() - arrived <= budget_s(query):
                live.append((arrived, query))
                continue
            finish([query])  # unanswered: the caller has stopped waiting
            self._expire([query], "expired in the queue")
        return live

    def _expire(self, queries: list[zenoh.Query], where: str) -> None:
        with self._expired_lock:
            self.expired += len(queries)
            expired = self.expired
        if expired == len(queries) or expired % 100 < len(queries):
            log.warning("%s: %d queries %s or before (their callers stopped waiting)",
                        self.service, expired, where)  # fmt: skip

    def _answer(self, queries: list[zenoh.Query], work: Batched) -> None:
        # Errors become ErrorReply at once: a kept exception's traceback would hold the queries
        # (and so their callers) until the garbage collector ran.
        started = time.perf_counter()
        accepted, requests = [], []
        for query in queries:
            try:
                requests.append(work.parse(query.payload.to_bytes() if query.payload else b""))
                accepted.append(query)
            except DeadlineExceeded:
                raise
            except Exception as exc:
                self._send(query, self._error(query, exc), started)
        if not accepted:
            return
        try:
            replies = list(work.run(requests))
            if len(replies) != len(accepted):
                raise RuntimeError(f"{len(replies)} replies for {len(accepted)} queries")
        except DeadlineExceeded:
            raise
        except Exception as exc:
            replies = [self._error(accepted[0], exc)] * len(accepted)
        for query, reply in zip(accepted, replies, strict=True):
            try:
                self._send(query, reply, started)
            except Exception:  # the others of the batch are still answered
                log.exception("%s could not answer %s", self.service, query.key_expr)

    def _send(self, query: zenoh.Query, reply: BaseModel, started: float) -> None:
        if not isinstance(reply, ErrorReply):
            try:
                payload = pack(reply)
            except Exception as exc:
                reply = self._error(query, exc)
            else:
                took = ReplyMeta(instance=self.instance, handler_ms=_ms_since(started))
                # congestion control: the query's
                query.reply(
                    query.key_expr, payload, encoding=MSGPACK, attachment=pack(took), express=True
                )
                return
        query.reply_err(pack(reply), encoding=MSGPACK)

    def _error(self, query: zenoh.Query, exc: Exception) -> ErrorReply:
        if isinstance(exc, ServiceUnavailable):
            return ErrorReply(code="unavailable", message=exc.reason, field=exc.service)
        if isinstance(exc, (MessageError, FieldError, TaskError)):
            return ErrorReply(code="bad_request", message=str(exc), field=_field_of(exc))
        trace = "".join(traceback.format_exception(exc))  # text: a record keeps no frames alive
        log.error("%s failed on %s\n%s", self.service, query.key_expr, trace)
        return ErrorReply(code="internal", message=f"{type(exc).__name__}: {exc}")

    def close(self) -> None:
        for queryable in self._queryables:
            queryable.undeclare()
        for pending in self._queues:
            pending.put(None)
        self.token.undeclare()


def finish(queries: Sequence[zenoh.Query]) -> None:
    """Finalize queries now, so that their callers see the end of the replies at once.

    Left to the garbage collector, a query lives as long as anything refers to it (a traceback
    in a reference cycle, say), and its caller waits until its own timeout.
    """
    for query in queries:
        with contextlib.suppress(Exception):  # already dropped
            query.drop()


def _ms_since(started: float) -> float:
    return (time.perf_counter() - started) * 1e3


def _field_of(exc: Exception) -> str | None:
    return getattr(exc, "field", None)
