"""`lsr serve ...`, `lsr router` and `lsr ping`: the long-running processes of the stack."""

from __future__ import annotations

import importlib
import socket
import sys
from collections.abc import Sequence
from pathlib import Path

import zenoh

from shared.bus import (
    SERVICES,
    BusConfig,
    close_quietly,
    host_id,
    instances,
    open_session,
    wait_for_stop_signal,
)
from shared.settings import Settings


def serve_service(service: str, settings: Settings, models: Sequence[Path] = ()) -> int:
    """One process of `service` for the model folders given (default: LSR_MODEL_DIR)."""
    if service not in SERVICES:
        raise ValueError(f"unknown service {service!r}; the services are {list(SERVICES)}")
    from services.runtime import run_service  # torch: not for the router and the gateway

    module = importlib.import_module(f"services.{service}.service")
    return run_service(service, module.setup, settings, models)


def serve_gateway(settings: Settings) -> int:
    import uvicorn

    from services.gateway.app import create_app

    print(f"gateway on http://{settings.host}:{settings.port} (docs at /docs)", flush=True)
    uvicorn.run(create_app(settings), host=settings.host, port=settings.port, log_level="warning")
    return 0


def serve_router(listen: Sequence[str], connect: Sequence[str] = ()) -> int:
    """A zenoh router as a Python session: what zenohd does, for machines without it.

    It loads LSR_ZENOH_CONFIG like every process: for the router, the access-control rules and
    the credentials dictionary (`shared.zenoh_access`). `connect`: the other routers of a mesh
    (one per host or site); a router retries them until they answer and after they drop."""
    config = BusConfig(
        mode="router", listen=listen, connect=connect, config_file=Settings().zenoh_config
    )
    session = zenoh.open(config.zenoh_config())
    print(f"zenoh router listening on {', '.join(listen)}", flush=True)
    wait_for_stop_signal()
    close_quietly(session)
    return 0


def ping(service: str, settings: Settings, this_host: bool, timeout_s: float = 2.0) -> int:
    """Exit 0 when an instance of `service` (on this host, if asked) answers: a health check."""
    config = settings.bus()
    config.open_timeout_s = timeout_s
    try:
        session = open_session(config)
    except ConnectionError as exc:
        print(f"{service}: {exc}", file=sys.stderr)
        return 1
    instance = f"{host_id()}-$*" if this_host else "*"
    asked = [instances(session, service, task, instance, timeout_s) for task in settings.tasks]
    found = [info for collect in asked for info in collect()]
    close_quietly(session)
    for info in found:
        print(
            f"{info.service} {info.instance}: task {info.task}, model {info.model_id}, "
            f"up {info.uptime_s:.0f} s"
        )
    if not found:
        where = f" on {socket.gethostname()}" if this_host else ""
        print(f"no {service} instance{where} answered within {timeout_s} s", file=sys.stderr)
        return 1
    return 0
