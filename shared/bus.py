"""Zenoh plumbing every process shares: sessions, key names, typed queries with deadlines.

Key layout (documented in docs/services.md):
  lsr/{service}/{task}/{operation}   queryables of the services (msgpack messages)
  lsr/alive/{service}/{instance}     liveliness tokens
  lsr/api/plan                       the public planning queryable (JSON, served by the gateway)
  lsr/robot/{robot_id}/plan          plans published for robots (JSON)
"""

from __future__ import annotations

import json
import logging
import os
import queue
import socket
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import zenoh
from pydantic import BaseModel

from shared.messages import ErrorReply, M, MessageError, pack, unpack

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


def robot_plan_key(robot_id: str) -> str:
    return f"lsr/robot/{robot_id}/plan"


API_PLAN_KEY = "lsr/api/plan"


def host_id() -> str:
    """The hostname, made safe for a key chunk."""
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in socket.gethostname())


def new_instance_id() -> str:
    """hostname-pid-random: unique per process, and says where it runs."""
    return f"{host_id()}-{os.getpid()}-{uuid.uuid4().hex[:6]}"


@dataclass
class BusConfig:
    """How a process joins the zenoh network: a client of routers, or the router itself."""

    connect: Sequence[str] = (DEFAULT_ENDPOINT,)
    mode: str = "client"
    listen: Sequence[str] = ()
    open_timeout_s: float | None = None  # None: keep retrying until a router answers

    def zenoh_config(self) -> zenoh.Config:
        config = zenoh.Config()
        config.insert_json5("mode", json.dumps(self.mode))
        config.insert_json5("scouting/multicast/enabled", "false")
        if self.mode != "router":
            config.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
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
                raise ConnectionError(f"no zenoh router at {list(config.connect)}: {exc}") from None
            log.warning("zenoh router at %s not reachable yet; retrying", list(config.connect))
            time.sleep(delay)
            delay = min(delay * 2, 2.0)


def close_quietly(session: zenoh.Session, timeout_s: float = 3.0) -> None:
    """Close a session, but never hang a shutdown on it."""
    closer = threading.Thread(target=session.close, daemon=True)
    closer.start()
    closer.join(timeout_s)


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


@dataclass
class PendingCall:
    """A query on its way; `result()` waits for the reply. Lets callers run queries in parallel."""

    session: zenoh.Session
    key: str
    service: str
    payload: bytes
    reply_type: type[BaseModel]
    deadline: float
    attempt_timeout_s: float
    replies: object = field(init=False)

    def __post_init__(self) -> None:
        self._send()

    def _send(self) -> None:
        timeout = max(0.05, min(self.attempt_timeout_s, self.deadline - time.monotonic()))
        self.replies = self.session.get(
            self.key,
            payload=self.payload,
            encoding=MSGPACK,
            target=zenoh.QueryTarget.BEST_MATCHING,
            congestion_control=zenoh.CongestionControl.BLOCK,
            timeout=timeout,
        )

    def result(self) -> BaseModel:
        unserved_since: float | None = None
        while True:
            started = time.monotonic()
            for reply in self.replies:  # type: ignore[attr-defined]
                if reply.ok is not None:
                    return _decode(self.service, reply.ok.payload.to_bytes(), self.reply_type)
                if reply.err.encoding != MSGPACK:  # zenoh's own "Timeout": no answer came
                    continue
                error: ErrorReply = _decode(self.service, reply.err.payload.to_bytes(), ErrorReply)
                if error.code == "unavailable":  # a service this one depends on is down
                    raise ServiceUnavailable(error.field or self.service, error.message)
                raise RemoteError(self.service, error)
            # No reply: nobody serves the key (the get ends at once), or an instance died with the
            # query. Ask again while the deadline allows, so that a live replica can take over; an
            # unserved key gets a short grace (routes settle) and then fails fast.
            now = time.monotonic()
            if now - started < 0.05:
                unserved_since = unserved_since or now
                if now - unserved_since > UNSERVED_GRACE_S or now > self.deadline:
                    raise ServiceUnavailable(self.service, f"no instance serves {self.key}")
                time.sleep(0.05)
            elif self.deadline - now < 0.05:
                raise ServiceUnavailable(self.service, f"no reply in time on {self.key}")
            self._send()


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
    attempt_timeout_s: float = 2.0,
) -> PendingCall:
    """Send a typed query to one instance of `service`; `.result()` returns a `reply_type`."""
    return PendingCall(
        session,
        service_key(service, task, operation),
        service,
        pack(request),
        reply_type,
        time.monotonic() + deadline_s,
        attempt_timeout_s,
    )


Handler = Callable[[bytes], BaseModel]


class Server:
    """Declares queryables for one service instance, each served by its own worker thread.

    Handlers raise MessageError or ValueError for a bad request; anything else is internal.
    Work happens off zenoh's callback threads, so a slow handler never stalls the network.
    """

    def __init__(self, session: zenoh.Session, service: str, instance: str) -> None:
        self.session = session
        self.service = service
        self.instance = instance
        self.token = session.liveliness().declare_token(alive_key(service, instance))
        self._queryables: list[zenoh.Queryable] = []
        self._queues: list[queue.Queue[zenoh.Query | None]] = []

    def serve(self, key: str, handler: Handler, workers: int = 1) -> None:
        pending: queue.Queue[zenoh.Query | None] = queue.Queue()
        self._queryables.append(self.session.declare_queryable(key, pending.put))
        self._queues.append(pending)
        for i in range(workers):
            thread = threading.Thread(
                target=self._loop, args=(pending, handler), name=f"{key}#{i}", daemon=True
            )
            thread.start()

    def _loop(self, pending: queue.Queue[zenoh.Query | None], handler: Handler) -> None:
        while (query := pending.get()) is not None:
            answer(query, handler, self.service)
            del query  # a query is finished when dropped: callers waiting on ALL see it at once

    def close(self) -> None:
        for queryable in self._queryables:
            queryable.undeclare()
        for pending in self._queues:
            pending.put(None)
        self.token.undeclare()


def answer(query: zenoh.Query, handler: Handler, service: str) -> None:
    """Run `handler` on a query's payload and reply with its message or an ErrorReply."""
    payload = query.payload.to_bytes() if query.payload is not None else b""
    try:
        reply = handler(payload)
    except ServiceUnavailable as exc:
        error = ErrorReply(code="unavailable", message=exc.reason, field=exc.service)
    except (MessageError, ValueError) as exc:
        error = ErrorReply(code="bad_request", message=str(exc), field=_field_of(exc))
    except Exception as exc:
        log.exception("%s failed on %s", service, query.key_expr)
        error = ErrorReply(code="internal", message=f"{type(exc).__name__}: {exc}")
    else:
        query.reply(query.key_expr, pack(reply), encoding=MSGPACK)  # congestion: the query's
        return
    query.reply_err(pack(error), encoding=MSGPACK)


def _field_of(exc: Exception) -> str | None:
    return getattr(exc, "field", None)
