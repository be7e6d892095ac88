"""The REST gateway: thin FastAPI routes over the zenoh services.

Routes are plain `def`s, so FastAPI runs them (and their blocking zenoh calls) in its thread pool,
never on the event loop. What they share with the zenoh API (`queries.py`) and the plan viewer
(`viewer.py`) lives in modules all of them import (`planning.py`, `errors.py`): none of the three
imports another's routes.
"""

from __future__ import annotations

import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import anyio
from fastapi import FastAPI, HTTPException, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response

from services.data.experience import ExperienceError
from services.gateway.auth import ApiKeys, load_digests
from services.gateway.errors import error_body
from services.gateway.middleware import ARRIVED, Admission, BodyLimit, GuardedRoute
from services.gateway.planning import Gateway, TaskNotServed
from services.gateway.queries import public_queries
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
    RemoteError,
    ServiceUnavailable,
    alive_key,
    close_quietly,
    new_instance_id,
    open_session,
)
from shared.settings import Settings
from shared.tasks import get_task, known_tasks
from shared.validation import FieldError


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
    # A request that brings camera frames (a body over LSR_LIGHT_BODY_BYTES) has a share of its
    # own, so that they never take the slots of plans from states or views.
    planning = frozenset({"/plan", "/render", "/experience"})
    for paths, limit, queue, heavy in [
        (planning, settings.max_in_flight, settings.max_queued, False),
        (planning, settings.max_frames_in_flight, settings.max_frames_queued, True),
        (
            frozenset({"/execute", "/execute/stream"}),
            settings.max_executing,
            settings.max_queued,
            None,
        ),
    ]:
        app.add_middleware(
            Admission,
            paths=paths,
            limit=limit,
            queue=queue,
            wait_s=settings.queue_wait_s,
            heavy=heavy,
            light_bytes=settings.light_body_bytes,
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
