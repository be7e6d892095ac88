"""The REST gateway: thin FastAPI routes over the zenoh services, plus the `lsr/api/plan` queryable.

Routes are plain `def`s, so FastAPI runs them (and their blocking zenoh calls) in its thread pool,
never on the event loop.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import Any

import anyio
import zenoh
from fastapi import FastAPI, HTTPException, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, ValidationError

from services.data.experience import ExperienceError
from services.gateway.auth import ApiKeys, load_digests
from services.gateway.inputs import BodyError, clip, error_detail, parse_json
from services.gateway.middleware import ARRIVED, Admission, BodyLimit, GuardedRoute
from services.gateway.planning import Gateway, TaskNotServed, plan_query_error
from services.gateway.schemas import (
    ExecuteRequest,
    ExecuteResponse,
    ExperienceRequest,
    ExperienceResponse,
    Health,
    PlanRequest,
    PlanResponse,
    RenderRequest,
    RenderResponse,
)
from services.gateway.viewer import add_viewer
from shared.bus import (
    API_PLAN_KEY,
    EXPERIENCE_KEYS,
    JSON,
    RemoteError,
    ServiceUnavailable,
    alive_key,
    close_quietly,
    experience_key,
    finish,
    new_instance_id,
    open_session,
)
from shared.settings import Settings
from shared.tasks import get_task, known_tasks
from shared.validation import FieldError

log = logging.getLogger(__name__)
API_PLAN_WORKERS = 4


def error_body(exc: Exception) -> tuple[int, Any] | None:
    """The HTTP status and `detail` for the errors the gateway expects; None for a bug.

    Details name the field and echo at most a short excerpt of the input (`inputs.error_detail`).
    """
    if isinstance(exc, BodyError):
        return exc.status, exc.detail()
    if isinstance(exc, FieldError):
        loc = ["body", *exc.field.split(".")]
        return 422, error_detail([{"loc": loc, "msg": str(exc), "type": "value_error"}])
    if isinstance(exc, ValidationError):
        return 422, error_detail(exc.errors(include_url=False), prefix=["body"])
    if isinstance(exc, RequestValidationError):  # FastAPI's: locations start with "body"
        return 422, error_detail(exc.errors())
    if isinstance(exc, TaskNotServed):
        return 404, clip(str(exc))
    if isinstance(exc, ExperienceError):  # the folder holds another model's experience
        return 409, clip(str(exc))
    if isinstance(exc, ServiceUnavailable):
        return 503, clip(str(exc))
    if isinstance(exc, RemoteError):
        return (422 if exc.error.code == "bad_request" else 502), clip(str(exc))
    return None


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


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        # Joining waits for a router; in a thread, so that uvicorn still hears SIGTERM meanwhile.
        session = await anyio.to_thread.run_sync(open_session, settings.bus())
        token = session.liveliness().declare_token(
            alive_key("gateway", settings.instance or new_instance_id())
        )
        app.state.gateway = Gateway(session, settings)
        stop_queries = public_queries(session, app.state.gateway, settings)
        yield
        stop_queries()
        token.undeclare()
        close_quietly(session)

    app = FastAPI(
        title="LSR planning gateway",
        version="1",
        description="Visual action plans from a Latent Space Roadmap (see docs/services.md).",
        lifespan=lifespan,
    )

    async def known_error(request: Request, exc: Exception) -> JSONResponse:
        status, detail = error_body(exc) or (500, "internal error")
        headers = {"Retry-After": "1"} if status == 503 else None
        return JSONResponse({"detail": detail}, status_code=status, headers=headers)

    for kind in (
        FieldError,
        TaskNotServed,
        ServiceUnavailable,
        RemoteError,
        ExperienceError,
        RequestValidationError,
    ):
        app.add_exception_handler(kind, known_error)
    app.router.route_class = GuardedRoute

    def gateway(request: Request) -> Gateway:
        return request.app.state.gateway

    @app.get("/health", response_model=Health, responses={503: {"model": Health}})
    def health(request: Request) -> JSONResponse:
        report = gateway(request).health()
        return JSONResponse(report.model_dump(), status_code=200 if report.status == "ok" else 503)

    @app.get("/tasks")
    def tasks() -> dict[str, list[str]]:
        """The tasks this deployment serves (every other known task gets 404 on the routes)."""
        return {"tasks": list(settings.tasks)}

    @app.get("/tasks/{task}")
    def task_info(task: str) -> dict[str, Any]:
        if task not in known_tasks():
            raise HTTPException(404, f"unknown task {task!r}; known tasks are {known_tasks()}")
        return get_task(task).info()

    def deadline(request: Request) -> float:
        """LSR_DEADLINE_S from the request's arrival: any wait for admission counts."""
        return request.scope.get(ARRIVED, time.monotonic()) + settings.deadline_s

    @app.post("/render")
    def render(body: RenderRequest, request: Request) -> RenderResponse:
        return gateway(request).render(body, deadline(request))

    @app.post("/plan", response_model=PlanResponse)
    def plan(body: PlanRequest, request: Request) -> Response:
        # Serialised by pydantic-core in one pass: plans carry many images, and FastAPI's own
        # re-validation of the returned model would cost more than the planning.
        response, timing = gateway(request).plan(body, deadline(request))
        headers = {"Server-Timing": timing}
        return Response(response.model_dump_json(), media_type="application/json", headers=headers)

    @app.post("/experience", response_model=ExperienceResponse)
    def experience(body: ExperienceRequest, request: Request) -> ExperienceResponse:
        """What a robot did, for the roadmap to grow from (`lsr roadmap grow`)."""
        return gateway(request).record(body, deadline(request))

    @app.post("/execute")
    def execute(body: ExecuteRequest, request: Request) -> ExecuteResponse:
        return gateway(request).execute(body)

    add_viewer(app)  # the plan viewer at / and the routes only its pictures need

    app.add_middleware(BodyLimit, limit=settings.max_body_bytes, timeout_s=settings.body_timeout_s)
    # Outermost: a request waiting for admission is not read yet. /execute holds its worker
    # for many seconds, so it has its own, smaller share.
    for paths, limit in [
        (frozenset({"/plan", "/render", "/experience"}), settings.max_in_flight),
        (frozenset({"/execute", "/execute/stream"}), settings.max_executing),
    ]:
        app.add_middleware(
            Admission,
            paths=paths,
            limit=limit,
            queue=settings.max_queued,
            wait_s=settings.queue_wait_s,
        )
    digests = load_digests(settings.api_key_hashes, settings.api_keys_file)
    if settings.require_api_keys and not digests:
        raise ValueError(
            "LSR_REQUIRE_API_KEYS is set, but LSR_API_KEY_HASHES and LSR_API_KEYS_FILE hold no "
            "key digest (make one with: python -m services.gateway.auth new)"
        )
    if digests:  # opt-in; outermost, so that strangers take no slot and no body is read
        app.add_middleware(ApiKeys, digests=digests)
    return app
