"""`lsr up`: a zenoh router, every service and the gateway as child processes on loopback.

One process per role serves every model folder (one a task) that needs it: services key their
operations by task, and a process per role and task would pay for the interpreter, torch and a
zenoh session once per task (`process_per_task`, as `lsr up --process-per-task`, does that).
The same launcher starts the stack for the end-to-end tests and benchmarks.
"""

from __future__ import annotations

import ctypes
import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

from shared.bus import SERVICES
from shared.settings import shipped_models


def _model_dataset(model_dir: Path) -> dict:
    path = Path(model_dir) / "vae" / "config.json"
    try:
        dataset = json.loads(path.read_text())["dataset"]
        if not isinstance(dataset["task"], str):
            raise TypeError
        return dataset
    except (OSError, ValueError, KeyError, TypeError):
        raise ValueError(f"{model_dir}: not a model folder (no task in {path})") from None


def model_task(model_dir: Path) -> str:
    """The task a model folder serves, as its VAE's config records it (no torch import)."""
    return _model_dataset(model_dir)["task"]


def declared_spec(model_dir: Path) -> dict | None:
    """The spec of a model's task when that task is defined by its data (no simulator)."""
    from shared.tasks import has_simulator

    dataset = _model_dataset(model_dir)
    return None if has_simulator(dataset["task"]) else dataset.get("spec")


def model_services(model_dir: Path) -> tuple[str, ...]:
    """The services a model needs: no sim for a task without a simulator."""
    from shared.tasks import has_simulator

    if has_simulator(model_task(model_dir)):
        return SERVICES
    return tuple(s for s in SERVICES if s != "sim")


@dataclass
class StackConfig:
    host: str = "127.0.0.1"
    port: int = 8000
    zenoh_port: int = 7447
    models: tuple[Path, ...] = field(default_factory=shipped_models)  # one folder a task
    log_dir: Path | None = None  # None: children write to this terminal
    env: dict[str, str] = field(default_factory=dict)
    # Files of `shared.zenoh_access.write_deployment`: each child gets its role's file as
    # LSR_ZENOH_CONFIG (the router: router.json5). None: an open bus, for loopback development.
    zenoh_access: Path | None = None
    process_per_task: bool = False  # True: a process per role and task, not per role
    # Encoder processes (replicas: the same keys, callers spread over them), for more camera
    # frames a second: each decodes and registers frames in its own worker
    encoders: int = 1

    def __post_init__(self) -> None:
        self.models = tuple(Path(m) for m in self.models)
        if not self.models:
            raise ValueError("no model folders to serve")
        tasks = [model_task(m) for m in self.models]
        if len(set(tasks)) != len(tasks):
            raise ValueError(f"two model folders serve the same task: {tasks}")
        if self.encoders < 1:
            raise ValueError(f"encoders must be at least 1, got {self.encoders}")

    @property
    def tasks(self) -> list[str]:
        return [model_task(m) for m in self.models]

    @property
    def task_specs(self) -> dict[str, dict]:
        """The specs of the served tasks that are defined by their data, by task."""
        specs = {model_task(m): declared_spec(m) for m in self.models}
        return {task: spec for task, spec in specs.items() if spec is not None}

    @property
    def endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.zenoh_port}"

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"


def _die_with_parent() -> None:
    """Children get SIGTERM if the launcher dies without stopping them (Linux)."""
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


class Stack:
    """Child processes by name; stopping the stack stops every one of them."""

    def __init__(self, config: StackConfig) -> None:
        self.config = config
        self.processes: dict[str, subprocess.Popen] = {}
        self._logs: list[IO] = []

    def _spawn(self, name: str, args: list[str], role: str) -> subprocess.Popen:
        if name in self.processes and self.processes[name].poll() is None:
            raise RuntimeError(f"{name} is already running")
        env = {
            **os.environ,
            "LSR_ZENOH_CONNECT": self.config.endpoint,
            "LSR_TASKS": json.dumps(self.config.tasks),
            "LSR_TASK_SPECS": json.dumps(self.config.task_specs),
            "PYTHONUNBUFFERED": "1",
            **self.config.env,
        }
        if self.config.zenoh_access is not None:
            env["LSR_ZENOH_CONFIG"] = str(self.config.zenoh_access / f"{role}.json5")
        out: IO | None = None
        if self.config.log_dir is not None:
            self.config.log_dir.mkdir(parents=True, exist_ok=True)
            out = open(self.config.log_dir / f"{name}.log", "ab")  # noqa: SIM115
            self._logs.append(out)
        process = subprocess.Popen(
            [sys.executable, "-m", "services.cli", *args],
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT if out else None,
            start_new_session=True,  # Ctrl-C reaches `lsr up`, which then stops the children
            preexec_fn=_die_with_parent,
        )
        self.processes[name] = process
        return process

    def start_router(self) -> None:
        listen = ["router", "--listen", f"tcp/127.0.0.1:{self.config.zenoh_port}"]
        self._spawn("router", listen, "router")

    def start_service(
        self, service: str, name: str | None = None, model: Path | None = None
    ) -> subprocess.Popen:
        """One process of `service`: for `model` (named `service-task`), or for every model
        that needs the service (named `service`)."""
        models = [model] if model else self.models_needing(service)
        if not models:
            raise ValueError(f"no model folder of this stack needs a {service}")
        name = name or (f"{service}-{model_task(model)}" if model else service)
        args = ["serve", service, *(a for m in models for a in ("--model", str(m)))]
        return self._spawn(name, args, service)

    def _replicas(self, service: str, name: str) -> list[str]:
        """The process names of `service`: `name`, then `name-2`, ... for encoder replicas."""
        count = self.config.encoders if service == "encoder" else 1
        return [name, *(f"{name}-{k}" for k in range(2, count + 1))]

    def models_needing(self, service: str) -> list[Path]:
        return [m for m in self.config.models if service in model_services(m)]

    def start_gateway(self) -> None:
        args = ["serve", "gateway", "--host", self.config.host, "--port", str(self.config.port)]
        self._spawn("gateway", args, "gateway")

    def start(self) -> None:
        self.start_router()
        self._wait_for_router()
        if self.config.process_per_task:
            for model in self.config.models:
                for service in model_services(model):
                    for name in self._replicas(service, f"{service}-{model_task(model)}"):
                        self.start_service(service, name, model=model)
        else:
            for service in SERVICES:
                if self.models_needing(service):
                    for name in self._replicas(service, service):
                        self.start_service(service, name)
        self.start_gateway()

    def _wait_for_router(self, timeout_s: float = 15.0) -> None:
        """The services retry until the router listens, but quietly is nicer."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and self.processes["router"].poll() is None:
            with socket.socket() as probe:
                if probe.connect_ex(("127.0.0.1", self.config.zenoh_port)) == 0:
                    return
            time.sleep(0.1)

    def health(self, timeout_s: float = 5.0) -> tuple[int, dict]:
        return gateway_health(self.config.url, timeout_s)

    def wait_healthy(
        self, timeout_s: float = 60.0, interrupted: Callable[[], bool] = lambda: False
    ) -> float:
        """Seconds until /health said 200; RuntimeError naming what is down otherwise."""
        started = time.monotonic()
        report: dict = {}
        while time.monotonic() - started < timeout_s:
            if interrupted():
                raise RuntimeError("interrupted during start-up")
            dead = [n for n, p in self.processes.items() if p.poll() is not None]
            if dead:
                raise RuntimeError(f"exited during start-up: {dead}")
            status, report = self.health()
            if status == 200:
                return time.monotonic() - started
            time.sleep(0.5)
        raise RuntimeError(f"not healthy after {timeout_s:.0f} s: {report.get('detail', report)}")

    def stop(self, name: str, sig: int = signal.SIGTERM, timeout_s: float = 10.0) -> None:
        process = self.processes.pop(name)
        if process.poll() is None:
            process.send_signal(sig)
            try:
                process.wait(timeout_s)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()

    def stop_all(self, timeout_s: float = 10.0) -> None:
        """Signal every child at once, then wait for them together."""
        for process in self.processes.values():
            if process.poll() is None:
                process.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + timeout_s
        for name in list(self.processes):
            self.stop(name, timeout_s=max(0.1, deadline - time.monotonic()))
        for log in self._logs:
            log.close()
        self._logs.clear()

    def __enter__(self) -> Stack:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop_all()


def gateway_health(url: str, timeout_s: float = 5.0) -> tuple[int, dict]:
    """(status, report) of a gateway's /health; (0, {}) when nothing answers."""
    try:
        with urllib.request.urlopen(f"{url}/health", timeout=timeout_s) as r:
            return r.status, json.loads(r.read())
    except urllib.error.HTTPError as exc:
        return exc.code, json.loads(exc.read() or b"{}")
    except (urllib.error.URLError, ConnectionError, TimeoutError):
        return 0, {}


def free_port() -> int:
    """A loopback port nobody listens on now (for tests and benchmarks)."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def check_ports_free(config: StackConfig) -> None:
    """A stack already running on these ports would answer our health checks: refuse to start."""
    for host, port, what in (
        (config.host, config.port, "--port"),
        ("127.0.0.1", config.zenoh_port, "--zenoh-port"),
    ):
        with socket.socket() as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as servers do
            try:
                probe.bind((host, port))
            except OSError as exc:
                raise ValueError(
                    f"{host}:{port} is not free ({exc.strerror}); choose {what}"
                ) from None


def run_up(config: StackConfig, healthy_timeout_s: float = 60.0) -> int:
    """Start everything, say where it is, and stop everything on Ctrl-C or SIGTERM."""
    check_ports_free(config)
    stopping = False

    def request_stop(*_: object) -> None:
        nonlocal stopping
        stopping = True

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, request_stop)
    with Stack(config) as stack:
        stack.start()
        try:
            seconds = stack.wait_healthy(healthy_timeout_s, interrupted=lambda: stopping)
        except RuntimeError as exc:
            print(f"lsr up: {exc}", file=sys.stderr)
            return 0 if stopping else 1
        print(f"LSR is up in {seconds:.1f} s: {config.url} (API docs: {config.url}/docs)")
        print(f"zenoh router: {config.endpoint}. Ctrl-C stops everything.", flush=True)
        while not stopping:
            dead = [n for n, p in stack.processes.items() if p.poll() is not None]
            if dead:
                print(f"lsr up: {dead} exited; stopping the stack", file=sys.stderr)
                return 1
            time.sleep(0.5)
        print("stopping", flush=True)
    return 0
