"""`lsr serve`, `router`, `ping` and `up`: the service stack."""

from __future__ import annotations

import argparse
from pathlib import Path

from services.cli.common import env_settings
from shared.settings import shipped_models


def cmd_serve(args: argparse.Namespace) -> int:
    from services.serve import serve_gateway, serve_service

    models = args.model or []
    settings = env_settings(
        zenoh_connect=args.connect,
        model_dir=models[0] if models else None,
        instance=args.instance,
        host=args.host,
        port=args.port,
    )
    if args.service == "gateway":
        return serve_gateway(settings)
    return serve_service(args.service, settings, models)


def cmd_router(args: argparse.Namespace) -> int:
    from services.serve import serve_router

    return serve_router(args.listen, args.connect)


def cmd_ping(args: argparse.Namespace) -> int:
    from services.serve import ping

    settings = env_settings(zenoh_connect=args.connect)
    return ping(args.service, settings, args.this_host, args.timeout)


def cmd_up(args: argparse.Namespace) -> int:
    from services.stack import StackConfig, run_up

    models = tuple(args.model) if args.model else shipped_models()
    config = StackConfig(
        host=args.host,
        port=args.port,
        zenoh_port=args.zenoh_port,
        models=models,
        zenoh_access=args.zenoh_access,
        process_per_task=args.process_per_task,
        encoders=args.encoders,
    )
    return run_up(config)


def register(sub: argparse._SubParsersAction) -> None:
    serve = sub.add_parser("serve", help="run one service (or the gateway) until SIGINT/SIGTERM")
    serve.add_argument("service", choices=["encoder", "planner", "apn", "sim", "gateway"])
    serve.add_argument(
        "--model",
        type=Path,
        action="append",
        help="model folder (env LSR_MODEL_DIR); repeat it to serve several tasks in one process",
    )
    serve.add_argument("--connect", help="zenoh router endpoints (env LSR_ZENOH_CONNECT)")
    serve.add_argument("--instance", help="instance id (default hostname-pid-random)")
    serve.add_argument("--host", help="gateway: address to bind (env LSR_HOST)")
    serve.add_argument("--port", type=int, help="gateway: port (env LSR_PORT)")
    serve.set_defaults(handler=cmd_serve)

    router = sub.add_parser("router", help="a zenoh router (a Python session in router mode)")
    router.add_argument("--listen", nargs="+", default=["tcp/127.0.0.1:7447"])
    router.add_argument(
        "--connect", nargs="*", default=[], help="other routers to mesh with (their endpoints)"
    )
    router.set_defaults(handler=cmd_router)

    ping = sub.add_parser("ping", help="exit 0 when a service answers (container health check)")
    ping.add_argument("service", choices=["encoder", "planner", "apn", "sim"])
    ping.add_argument("--this-host", action="store_true", help="only instances on this host")
    ping.add_argument("--connect", help="zenoh router endpoints (env LSR_ZENOH_CONNECT)")
    ping.add_argument("--timeout", type=float, default=2.0)
    ping.set_defaults(handler=cmd_ping)

    up = sub.add_parser("up", help="start the whole stack on loopback; Ctrl-C stops it")
    up.add_argument("--host", default="127.0.0.1")
    up.add_argument("--port", type=int, default=8000)
    up.add_argument("--zenoh-port", type=int, default=7447)
    up.add_argument(
        "--model",
        type=Path,
        action="append",
        help="a model folder to serve, once per task (default: every shipped model)",
    )
    up.add_argument(
        "--zenoh-access",
        type=Path,
        help="a folder written by python -m shared.zenoh_access: run the bus under its access "
        "control, each process with its role's credentials (default: an open loopback bus)",
    )
    up.add_argument(
        "--process-per-task",
        action="store_true",
        help="a process per service and task (default: one per service for every task)",
    )
    up.add_argument(
        "--encoders",
        type=int,
        default=1,
        help="encoder processes (replicas), for more camera frames a second (default 1)",
    )
    up.set_defaults(handler=cmd_up)
