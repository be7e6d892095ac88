"""The gateway's public zenoh API: `lsr/api/plan` and `lsr/experience/{task}`, the twins of
`POST /plan` and `POST /experience`, answered by worker threads beside the HTTP routes."""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh
from pydantic import BaseModel

from services.gateway.errors import error_body
from services.gateway.inputs import BodyError, clip, parse_json
from services.gateway.planning import Gateway, plan_query_error
from services.gateway.schemas import ExperienceRequest, PlanRequest
from shared.bus import API_PLAN_KEY, EXPERIENCE_KEYS, JSON, experience_key, finish
from shared.settings import Settings
from shared.validation import FieldError

log = logging.getLogger(__name__)
API_PLAN_WORKERS = 4

# An answer to one query: its parsed JSON body and key in, the reply body out.
Answer = Callable[[Any, str, float], BaseModel]


def serve_queries(
    session: zenoh.Session, key: str, answer: Answer, settings: Settings, workers: int
) -> Callable[[], None]:
    """A public zenoh API key (`lsr/api/plan`, `lsr/experience/*`): the JSON body of the REST
    route in, the same JSON as its reply out, errors as {"status", "detail"}.

    Like REST, it sheds load: a query arriving while `settings.max_queued` wait gets 503 at
    once, and one still queued at its deadline (LSR_DEADLINE_S from arrival) gets 503 unworked.
    """
    pending: queue.Queue[tuple[float, zenoh.Query] | None] = queue.Queue()

    def arrived(query: zenoh.Query) -> None:
        if pending.qsize() >= settings.max_queued:
            overloaded(query, f"{pending.qsize()} queries waiting")
            return
        pending.put((time.monotonic(), query))

    queryable = session.declare_queryable(key, arrived, complete=True)

    def work() -> None:
        while (item := pending.get()) is not None:
            came, query = item
            deadline = came + settings.deadline_s
            try:
                if time.monotonic() >= deadline:
                    overloaded(query, "waited past its deadline")
                else:
                    answer_query(query, answer, settings.max_body_bytes, deadline)
            except Exception:  # a reply that could not be sent must not end the worker
                log.exception("could not answer %s", key)
            finally:
                finish([query])
            del item, query

    for i in range(workers):
        threading.Thread(target=work, name=f"{key}#{i}", daemon=True).start()

    def stop() -> None:
        queryable.undeclare()
        for _ in range(workers):
            pending.put(None)

    return stop


def overloaded(query: zenoh.Query, why: str) -> None:
    try:
        query.reply_err(plan_query_error(503, f"gateway overloaded: {why}"), encoding=JSON)
    finally:
        finish([query])


def answer_query(query: zenoh.Query, answer: Answer, max_bytes: int, deadline: float) -> None:
    """Answer one query; every query gets a reply, an error one at worst."""
    payload = query.payload.to_bytes() if query.payload is not None else b""
    try:
        if len(payload) > max_bytes:
            raise BodyError(413, ["body"], f"payload over {max_bytes} bytes", "too_large")
        response = answer(parse_json(payload), str(query.key_expr), deadline)
    except Exception as exc:
        known = error_body(exc)
        if known is None:
            log.exception("%s failed", query.key_expr)
            known = (500, clip(f"{type(exc).__name__}: {exc}"))
        query.reply_err(plan_query_error(*known), encoding=JSON)
        return
    query.reply(query.key_expr, response.model_dump_json(), encoding=JSON)


def public_queries(
    session: zenoh.Session, gateway: Gateway, settings: Settings
) -> Callable[[], None]:
    """The zenoh twins of POST /plan and POST /experience."""

    def plan(body: Any, _: str, deadline: float) -> BaseModel:
        return gateway.plan(PlanRequest.model_validate(body), deadline)[0]

    def experience(body: Any, key: str, deadline: float) -> BaseModel:
        request = ExperienceRequest.model_validate(body)
        if key != experience_key(request.task):
            raise FieldError("task", f"reported on {key}, the body says {request.task!r}")
        return gateway.record(request, deadline)

    stops = [
        serve_queries(session, API_PLAN_KEY, plan, settings, API_PLAN_WORKERS),
        serve_queries(session, EXPERIENCE_KEYS, experience, settings, 1),
    ]

    def stop_all() -> None:
        for stop in stops:
            stop()

    return stop_all
