"""The REST gateway: thin FastAPI routes over the zenoh services, plus the `lsr/api/plan` queryable.

Routes are plain `def`s, so FastAPI runs them (and their blocking zenoh calls) in its thread pool,
never on the event loop.
"""

from __future__ import annotations

import json
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
from fastapi.routing import APIRoute
from pydantic import ValidationError
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from services.gateway.auth import ApiKeys, load_digests
from services.gateway.inputs import BodyError, clip, error_detail, parse_json
from services.gateway.planning import Gateway, plan_query_error
from services.gateway.schemas import (
    ExecuteRequest,
    ExecuteResponse,
    Health,
    PlanRequest,
    PlanResponse,
    RenderRequest,
    RenderResponse,
)
from shared.bus import (
    API_PLAN_KEY,
    JSON,
    RemoteError,
    ServiceUnavailable,
    alive_key,
    close_quietly,
    finish,
    new_instance_id,
    open_session,
)
from shared.settings import Settings
from shared.tasks import get_task, task_names
from shared.validation import FieldError

log = logging.getLogger(__name__)
API_PLAN_WORKERS = 4
ARRIVED = "lsr.arrived"  # scope key: when Admission first saw the request (time.monotonic())


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
    if isinstance(exc, ServiceUnavailable):
        return 503, clip(str(exc))
    if isinstance(exc, RemoteError):
        return (422 if exc.error.code == "bad_request" else 502), clip(str(exc))
    return None


def is_json(content_type: str | None) -> bool:
    kind = (content_type or "").split(";", 1)[0].strip().lower()
    return kind == "application/json" or (
        kind.startswith("application/") and kind.endswith("+json")
    )


class GuardedRequest(Request):
    """A request whose JSON body is parsed within limits (`inputs.parse_json`), not as FastAPI
    would: any size of structure, then every error echoed with its whole input."""

    async def json(self) -> Any:
        if not hasattr(self, "_json"):
            try:
                self._json = parse_json(await self.body())
            except BodyError as exc:
                raise HTTPException(exc.status, exc.detail()) from None
        return self._json


class GuardedRoute(APIRoute):
    """Routes that take JSON bodies only, parsed by GuardedRequest."""

    def get_route_handler(self) -> Callable[[Request], Any]:
        handler = super().get_route_handler()
        takes_body = self.body_field is not None

        async def guarded(request: Request) -> Response:
            if takes_body and not is_json(request.headers.get("content-type")):
                # Anything else would reach validation as raw bytes (and their echo as a 500).
                detail = error_detail(
                    [
                        {
                            "loc": ["header", "content-type"],
                            "msg": "send the body as application/json",
                            "type": "unsupported_media_type",
                            "input": request.headers.get("content-type"),
                        }
                    ]
                )
                return JSONResponse({"detail": detail}, status_code=415)
            return await handler(GuardedRequest(request.scope, request.receive))

        return guarded


class BodyLimit:
    """Answers 413 to bodies over `limit` bytes, declared or streamed, before anyone reads them,
    and 408 to bodies not complete `timeout_s` after the request began (clients that dribble a
    body would otherwise hold a connection and a worker for ever). Both close the connection.
    """

    def __init__(self, app: ASGIApp, limit: int, timeout_s: float | None = None) -> None:
        self.app = app
        self.limit = limit
        self.timeout_s = timeout_s

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.limit:
            return await self._refuse(send, 413, f"request body over {self.limit} bytes")
        deadline = None if self.timeout_s is None else time.monotonic() + self.timeout_s
        received = 0
        complete = refused = False

        async def limited() -> Message:
            nonlocal received, complete, refused
            if refused:
                return {"type": "http.disconnect"}
            if complete or deadline is None:
                message = await receive()
            else:
                with anyio.move_on_after(max(0.0, deadline - time.monotonic())) as waiting:
                    message = await receive()
                    complete = not message.get("more_body", False)
                if waiting.cancelled_caught:
                    refused = True
                    detail = f"request body not complete within {self.timeout_s} s"
                    await self._refuse(send, 408, detail)
                    return {"type": "http.disconnect"}  # the app stops reading here
            received += len(message.get("body", b""))
            if received > self.limit:
                refused = True
                await self._refuse(send, 413, f"request body over {self.limit} bytes")
                return {"type": "http.disconnect"}
            return message

        async def unless_refused(message: Message) -> None:
            if not refused:  # whatever the app answers after a refusal is dropped
                await send(message)

        await self.app(scope, limited, unless_refused)

    async def _refuse(self, send: Send, status: int, detail: str) -> None:
        body = json.dumps({"detail": detail}).encode()
        headers = [
            (b"content-type", b"application/json"),
            (b"content-length", b"%d" % len(body)),
            (b"connection", b"close"),  # the rest of the body is never read
        ]
        await send({"type": "http.response.start", "status": status, "headers": headers})
        await send({"type": "http.response.body", "body": body})


class Admission:
    """Sheds what the gateway cannot serve in time, quickly, instead of queueing without bound.

    At most `limit` requests to `paths` are in progress; the next ones wait for a slot, at most
    `queue` of them and each at most `wait_s`. A request that would wait longer than that (by the
    recent time per request and the queue ahead of it), or find the queue full, gets 503 at once
    (`Retry-After: 1`); one whose wait runs out gets it then. A waiting request holds no body in
    memory (it is not read yet). Each request's arrival time goes into its scope (`ARRIVED`),
    so that its deadline counts the wait.
    """

    def __init__(
        self, app: ASGIApp, paths: frozenset[str], limit: int, queue: int, wait_s: float
    ) -> None:
        self.app = app
        self.paths = paths
        self.limit = limit
        self.queue = queue
        self.wait_s = wait_s
        self.waiting = 0
        self.service_s: float | None = None  # moving average of a request's time in progress
        self._slots: anyio.Semaphore | None = None  # made on the event loop, on first use

    def expected_wait_s(self) -> float:
        if self._slots is None or self._slots.value > 0 or self.service_s is None:
            return 0.0
        return (self.waiting + 1) * self.service_s / self.limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["path"] not in self.paths:
            return await self.app(scope, receive, send)
        scope[ARRIVED] = time.monotonic()
        if self._slots is None:
            self._slots = anyio.Semaphore(self.limit)
        if self._slots.value == 0 and (
            self.waiting >= self.queue or self.expected_wait_s() > self.wait_s
        ):
            return await self._overloaded(send)
        admitted = False
        self.waiting += 1
        try:
            with anyio.move_on_after(self.wait_s):
                await self._slots.acquire()
                admitted = True
        finally:
            self.waiting -= 1
        if not admitted:
            return await self._overloaded(send)
        started = time.monotonic()
        try:
            await self.app(scope, receive, send)
        finally:
            self._slots.release()
            took = time.monotonic() - started
            self.service_s = took if self.service_s is None else 0.9 * self.service_s + 0.1 * took

    async def _overloaded(self, send: Send) -> None:
        detail = f"gateway overloaded: {self.limit} requests in progress, {self.waiting} waiting"
        body = json.dumps({"detail": detail}).encode()
        headers = [
            (b"content-type", b"application/json"),
            (b"content-length", b"%d" % len(body)),
            (b"retry-after", b"1"),
        ]
        await send({"type": "http.response.start", "status": 503, "headers": headers})
        await send({"type": "http.response.body", "body": body})


def serve_plan_queries(
    session: zenoh.Session, gateway: Gateway, settings: Settings
) -> Callable[[], None]:
    """`lsr/api/plan`: a JSON body of POST /plan in, the same JSON as the REST reply out.

    Like REST, it sheds load: a query arriving while `settings.max_queued` wait gets 503 at
    once, and one still queued at its deadline (LSR_DEADLINE_S from arrival) gets 503 unworked.
    """
    pending: queue.Queue[tuple[float, zenoh.Query] | None] = queue.Queue()

    def arrived(query: zenoh.Query) -> None:
        if pending.qsize() >= settings.max_queued:
            overloaded(query, f"{pending.qsize()} queries waiting")
            return
        pending.put((time.monotonic(), query))

    queryable = session.declare_queryable(API_PLAN_KEY, arrived, complete=True)

    def work() -> None:
        while (item := pending.get()) is not None:
            came, query = item
            deadline = came + settings.deadline_s
            try:
                if time.monotonic() >= deadline:
                    overloaded(query, "waited past its deadline")
                else:
                    answer_plan_query(query, gateway, settings.max_body_bytes, deadline)
            except Exception:  # a reply that could not be sent must not end the worker
                log.exception("could not answer %s", API_PLAN_KEY)
            finally:
                finish([query])
            del item, query

    for i in range(API_PLAN_WORKERS):
        threading.Thread(target=work, name=f"api-plan#{i}", daemon=True).start()

    def stop() -> None:
        queryable.undeclare()
        for _ in range(API_PLAN_WORKERS):
            pending.put(None)

    return stop


def overloaded(query: zenoh.Query, why: str) -> None:
    try:
        query.reply_err(plan_query_error(503, f"gateway overloaded: {why}"), encoding=JSON)
    finally:
        finish([query])


def answer_plan_query(
    query: zenoh.Query, gateway: Gateway, max_bytes: int, deadline: float | None = None
) -> None:
    """Answer one `lsr/api/plan` query; every query gets a reply, an error one at worst."""
    payload = query.payload.to_bytes() if query.payload is not None else b""
    try:
        if len(payload) > max_bytes:
            raise BodyError(413, ["body"], f"payload over {max_bytes} bytes", "too_large")
        response, _ = gateway.plan(PlanRequest.model_validate(parse_json(payload)), deadline)
    except Exception as exc:
        known = error_body(exc)
        if known is None:
            log.exception("lsr/api/plan failed")
            known = (500, clip(f"{type(exc).__name__}: {exc}"))
        query.reply_err(plan_query_error(*known), encoding=JSON)
        return
    query.reply(query.key_expr, response.model_dump_json(), encoding=JSON)


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
        stop_queries = serve_plan_queries(session, app.state.gateway, settings)
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

    for kind in (FieldError, ServiceUnavailable, RemoteError, RequestValidationError):
        app.add_exception_handler(kind, known_error)
    app.router.route_class = GuardedRoute

    def gateway(request: Request) -> Gateway:
        return request.app.state.gateway

    @app.get("/health", response_model=Health, responses={503: {"model": Health}})
    def health(request: Request) -> JSONResponse:
        report = gateway(request).health()
        return JSONResponse(report.model_dump(), status_code=200 if report.status == "ok" else 503)

    @app.get("/tasks/{task}")
    def task_info(task: str) -> dict[str, Any]:
        if task not in task_names():
            raise HTTPException(404, f"unknown task {task!r}; known tasks are {task_names()}")
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

    @app.post("/execute")
    def execute(body: ExecuteRequest, request: Request) -> ExecuteResponse:
        return gateway(request).execute(body)

    app.add_middleware(BodyLimit, limit=settings.max_body_bytes, timeout_s=settings.body_timeout_s)
    # Outermost: a request waiting for admission is not read yet. /execute holds its worker
    # for many seconds, so it has its own, smaller share.
    for paths, limit in [
        (frozenset({"/plan", "/render"}), settings.max_in_flight),
        (frozenset({"/execute"}), settings.max_executing),
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
