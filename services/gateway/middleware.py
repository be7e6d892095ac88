"""The gateway's ASGI layers, outside the routes: what a request must pass before any work.

From the outside in: API keys (`auth.ApiKeys`, when configured), admission (`Admission`: shed
what cannot be served in time), the body's size and arrival time (`BodyLimit`), and JSON bodies
parsed within limits (`GuardedRoute`).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from typing import Any

import anyio
from fastapi import HTTPException, Request
from fastapi.responses import JSONResponse, Response
from fastapi.routing import APIRoute
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from services.gateway.inputs import BodyError, error_detail, parse_json


async def send_json(
    send: Send, status: int, detail: str, headers: list[tuple[bytes, bytes]] = ()
) -> None:
    """A `{"detail": ...}` JSON reply sent by ASGI middleware, before or instead of the app."""
    body = json.dumps({"detail": detail}).encode()
    head = [
        (b"content-type", b"application/json"),
        (b"content-length", b"%d" % len(body)),
        *headers,
    ]
    await send({"type": "http.response.start", "status": status, "headers": head})
    await send({"type": "http.response.body", "body": body})


ARRIVED = "lsr.arrived"  # scope key: when Admission first saw the request (time.monotonic())


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
        # connection: close, as the rest of the body is never read
        await send_json(send, status, detail, [(b"connection", b"close")])


class Admission:
    """Sheds what the gateway cannot serve in time, quickly, instead of queueing without bound.

    At most `limit` requests to `paths` are in progress; the next ones wait for a slot, at most
    `queue` of them and each at most `wait_s`. A request that would wait longer than that (by
    the recent time per request and the queue ahead of it), or find the queue full, gets 503 at
    once (`Retry-After: 1`); one whose wait runs out gets it then. With `heavy` set a share
    takes only heavy requests (camera frames: bodies over `light_bytes`) or only light ones, so
    that a flood of frames never takes the slots of plans from states or views. A waiting
    request holds no body in memory (it is not read yet). Each request's arrival time goes into
    its scope (`ARRIVED`, set by the first share it meets), so that its deadline counts the
    wait.
    """

    def __init__(
        self,
        app: ASGIApp,
        paths: frozenset[str],
        limit: int,
        queue: int,
        wait_s: float,
        heavy: bool | None = None,
        light_bytes: int = 0,
    ) -> None:
        self.app = app
        self.paths = paths
        self.heavy = heavy
        self.light_bytes = light_bytes
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

    def takes(self, scope: Scope) -> bool:
        """Whether this share admits the request: every one to its paths, or (`heavy` set) only
        the heavy ones (bodies over `light_bytes`, or of a length not declared) or the light."""
        if scope["type"] != "http" or scope["path"] not in self.paths:
            return False
        if self.heavy is None:
            return True
        declared = dict(scope["headers"]).get(b"content-length", b"")
        heavy = not declared.isdigit() or int(declared) > self.light_bytes
        return heavy == self.heavy

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if not self.takes(scope):
            return await self.app(scope, receive, send)
        scope.setdefault(ARRIVED, time.monotonic())
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
        await send_json(send, 503, detail, [(b"retry-after", b"1")])
