"""The stack across three hosts, and what it does when one fails (issue 23). Needs root.

Three network namespaces on a bridge stand for three hosts with their own addresses and links:

  host a (10.77.0.1)  router, encoder, planner, APN, sim, gateway
  host b (10.77.0.2)  router, encoder, planner, APN, sim, gateway
  host c (10.77.0.3)  router, robots (bounded plan loops over `lsr/api/plan`)

Each host runs one router (`lsr router`) that meshes with the others over TLS; every process
authenticates with its own role's credentials and the routers apply the access-control rules of
`shared.zenoh_access` (deny by default). Every process is started by the project's own commands
with the generated files; they are printed with --show-commands (the deployment guide,
docs/services.md). Under the robots' load it then:

  kill      kills host a's services (SIGKILL): no request may fail while host b serves;
  cut       cuts host a's link for --cut-s seconds: requests are served by host b or answered
            503 within the deadline, never left hanging; after the link returns, host a's
            services are back in gateway b's /health without a restart (recovery time);
  router    kills host b's router and starts it again: its processes reconnect on their own;
  impostor  on host c, a process with a robot's (valid) credentials declares the planner's keys
            and a liveliness token, and one with a wrong password tries to join: neither gets
            a query or shows in /health.

Prints one JSON line (requests, failures, slowest answer, recovery times, per phase) and exits 1
when a check fails. All traffic stays on this machine; the namespaces go when it ends.

    sudo .venv/bin/python benchmarks/mesh_faults.py            # about 2.5 minutes
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from services.stack import gateway_health
from shared.bus import SERVICES
from shared.zenoh_access import write_deployment

ROOT = Path(__file__).resolve().parents[1]
SUBNET = "10.77.0"
HOSTS = {"a": f"{SUBNET}.1", "b": f"{SUBNET}.2", "c": f"{SUBNET}.3"}
SERVICE_HOSTS = ("a", "b")
ROBOT_HOST = "c"
BRIDGE_ADDRESS = f"{SUBNET}.254/24"
ZENOH_PORT = 7447
GATEWAY_PORT = 8000
ROBOTS = ("arm-1", "arm-2")


def sh(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    return subprocess.run(args, check=check, capture_output=True, text=True)


@dataclass
class Network:
    """Namespaces `{prefix}-{host}` joined by the bridge `{prefix}br`; `cut` downs a host's port."""

    prefix: str
    made: list[str] = field(default_factory=list)

    def ns(self, host: str) -> str:
        return f"{self.prefix}-{host}"

    def port(self, host: str) -> str:
        return f"{self.prefix}{host}"

    @property
    def bridge(self) -> str:
        return f"{self.prefix}br"

    def up(self) -> None:
        sh("ip", "link", "add", self.bridge, "type", "bridge")
        self.made.append(self.bridge)
        sh("ip", "addr", "add", BRIDGE_ADDRESS, "dev", self.bridge)
        sh("ip", "link", "set", self.bridge, "up")
        for host, address in HOSTS.items():
            ns = self.ns(host)
            sh("ip", "netns", "add", ns)
            self.made.append(ns)
            sh("ip", "link", "add", self.port(host), "type", "veth", "peer", "name", "eth0",
               "netns", ns)  # fmt: skip
            sh("ip", "link", "set", self.port(host), "master", self.bridge, "up")
            sh("ip", "-n", ns, "addr", "add", f"{address}/24", "dev", "eth0")
            sh("ip", "-n", ns, "link", "set", "eth0", "up")
            sh("ip", "-n", ns, "link", "set", "lo", "up")

    def cut(self, host: str) -> None:
        sh("ip", "link", "set", self.port(host), "down")

    def restore(self, host: str) -> None:
        sh("ip", "link", "set", self.port(host), "up")

    def down(self) -> None:
        for name in reversed(self.made):
            if name == self.bridge:
                sh("ip", "link", "del", name, check=False)
            else:
                sh("ip", "netns", "del", name, check=False)  # its veth end goes with it
        self.made.clear()


@dataclass
class Hosts:
    """Processes by name, each started in its host's namespace by the project's commands."""

    network: Network
    access: Path  # the files of `python -m shared.zenoh_access`
    logs: Path
    model: Path
    show: bool = False
    processes: dict[str, subprocess.Popen] = field(default_factory=dict)
    _files: list[IO] = field(default_factory=list)

    def start(self, name: str, host: str, role: str, args: list[str]) -> None:
        """`lsr ARGS` in `host`, with its role's credentials, on the host's own router."""
        env = [
            f"LSR_ZENOH_CONFIG={self.access / f'{role}.json5'}",
            f"LSR_ZENOH_CONNECT=tcp/127.0.0.1:{ZENOH_PORT}",
        ]
        if self.show:
            print(f"[host {host}] {' '.join([*env, 'lsr', *args])}", file=sys.stderr, flush=True)
        out = open(self.logs / f"{name}.log", "ab")  # noqa: SIM115
        self._files.append(out)
        lsr = str(Path(sys.executable).parent / "lsr")
        self.processes[name] = subprocess.Popen(
            ["ip", "netns", "exec", self.network.ns(host), "env", *env, lsr, *args],
            stdout=out,
            stderr=subprocess.STDOUT,
            env={**os.environ, "PYTHONUNBUFFERED": "1", "MUJOCO_GL": "egl"},
            cwd=ROOT,
        )

    def router(self, host: str) -> None:
        listen = [f"tls/{HOSTS[host]}:{ZENOH_PORT}", f"tcp/127.0.0.1:{ZENOH_PORT}"]
        peers = [f"tls/{HOSTS[h]}:{ZENOH_PORT}" for h in HOSTS if h < host]
        args = ["router", "--listen", *listen] + (["--connect", *peers] if peers else [])
        self.start(f"router-{host}", host, "router", args)

    def service(self, host: str, service: str) -> None:
        args = ["serve", service, "--model", str(self.model), "--instance", f"{host}-{service}"]
        self.start(f"{service}-{host}", host, service, args)

    def gateway(self, host: str) -> None:
        args = ["serve", "gateway", "--host", HOSTS[host], "--port", str(GATEWAY_PORT)]
        self.start(f"gateway-{host}", host, "gateway", args)

    def kill(self, name: str, sig: int = signal.SIGKILL) -> None:
        process = self.processes.pop(name)
        if process.poll() is None:
            process.send_signal(sig)
        process.wait(10)

    def dead(self) -> list[str]:
        return [name for name, p in self.processes.items() if p.poll() is not None]

    def stop_all(self) -> None:
        for process in self.processes.values():
            if process.poll() is None:
                process.send_signal(signal.SIGTERM)
        for name in list(self.processes):
            try:
                self.processes[name].wait(10)
            except subprocess.TimeoutExpired:
                self.processes[name].kill()
        self.processes.clear()
        for out in self._files:
            out.close()


def health(host: str, timeout_s: float = 3.0) -> dict[str, Any]:
    """Gateway `host`'s /health (from this machine's end of the bridge); {} when unreachable."""
    return gateway_health(f"http://{HOSTS[host]}:{GATEWAY_PORT}", timeout_s)[1]


def instances(report: dict[str, Any]) -> set[str]:
    return {
        i["instance"] for s in report.get("services", {}).values() for i in s.get("instances", [])
    }


def wait_for(check: Any, timeout_s: float, every_s: float = 0.25) -> float | None:
    """Seconds until check() was true, None if it never was within timeout_s."""
    started = time.monotonic()
    while time.monotonic() - started < timeout_s:
        if check():
            return round(time.monotonic() - started, 2)
        time.sleep(every_s)
    return None


def any_of_host(host: str, gateway: str) -> bool:
    """Whether gateway `gateway`'s /health lists any instance of `host`'s services."""
    return any(i.startswith(f"{host}-") for i in instances(health(gateway)))


def both_hosts_serving(host: str) -> bool:
    seen = instances(health(host))
    return all(f"{h}-{s}" in seen for h in SERVICE_HOSTS for s in SERVICES)


# The robots' load: a process in host c's namespace ------------------------------------------


def load(args: argparse.Namespace) -> int:
    """Bounded plan loops, one thread per robot, through the project's robot client
    (`services.robot.RobotPlanner`: `lsr/api/plan`, then the plan on its own key), from images
    its own world renders; one JSON line a request."""
    import numpy as np

    from services.robot import RobotPlanner
    from services.sim.worlds import make_world
    from shared.bus import BusConfig, ServiceUnavailable, open_session
    from shared.plans import UnknownImageError

    rng = np.random.default_rng(args.seed)
    images = []
    with make_world("box_stacking", 64) as world:
        for _ in range(24):
            world.reset(world.task.sample_state(rng), rng)
            images.append(world.render())
    lock = threading.Lock()
    stop_at = time.monotonic() + args.duration_s

    def robot(robot_id: str, seed: int) -> None:
        config = BusConfig(connect=[f"tcp/127.0.0.1:{ZENOH_PORT}"], open_timeout_s=30,
                           config_file=args.access / f"robot-{robot_id}.json5")  # fmt: skip
        session = open_session(config)
        planner = RobotPlanner(session, robot_id, "box_stacking", timeout_s=args.timeout_s)
        pick = np.random.default_rng(seed)
        sent = 0
        while time.monotonic() < stop_at and sent < args.max_requests:
            start, goal = pick.choice(len(images), 2, replace=False)
            began = time.time()
            try:
                outcome = "ok" if planner.plan(images[start], images[goal], 1) else "no_path"
            except ServiceUnavailable as exc:
                outcome = "503" if exc.service == "planning" else "unanswered"
            except TimeoutError:
                outcome = "not_published"
            except UnknownImageError:
                outcome = "refused"
            except Exception as exc:  # anything else is a failure to count, not a dead robot
                outcome = f"error: {type(exc).__name__}"
            sent += 1
            with lock:
                print(json.dumps({"robot": robot_id, "t": round(began, 3), "outcome": outcome,
                                  "s": round(time.time() - began, 3)}), flush=True)  # fmt: skip
            time.sleep(args.pause_s)
        session.close()

    threads = [threading.Thread(target=robot, args=(r, i)) for i, r in enumerate(ROBOTS)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return 0


class Load:
    """The load process on the robot host; its lines, read as they come."""

    def __init__(self, hosts: Hosts, duration_s: float, timeout_s: float) -> None:
        args = ["load", "--access", str(hosts.access), "--duration-s", str(duration_s),
                "--timeout-s", str(timeout_s)]  # fmt: skip
        self.lines: list[dict[str, Any]] = []
        self.process = subprocess.Popen(
            ["ip", "netns", "exec", hosts.network.ns(ROBOT_HOST), sys.executable, __file__, *args],
            stdout=subprocess.PIPE,
            stderr=open(hosts.logs / "load.log", "ab"),  # noqa: SIM115
            text=True,
            cwd=ROOT,
        )
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            with contextlib.suppress(ValueError):
                self.lines.append(json.loads(line))

    def between(self, start: float, end: float) -> list[dict[str, Any]]:
        return [r for r in self.lines if start <= r["t"] < end]


def summary(records: list[dict[str, Any]]) -> dict[str, Any]:
    outcomes: dict[str, int] = {}
    for r in records:
        outcomes[r["outcome"]] = outcomes.get(r["outcome"], 0) + 1
    return {
        "requests": len(records),
        "ok": outcomes.get("ok", 0),
        "outcomes": outcomes,
        "slowest_s": max((r["s"] for r in records), default=None),
    }


# The run ------------------------------------------------------------------------------------


def run(args: argparse.Namespace) -> int:
    if os.geteuid() != 0:
        print("mesh_faults: needs root (network namespaces)", file=sys.stderr)
        return 2
    network = Network(prefix=f"lsm{os.getpid() % 10000}")
    work = Path(tempfile.mkdtemp(prefix="lsr-mesh-"))
    (work / "logs").mkdir()
    write_deployment(work / "zenoh", list(ROBOTS), tls_hosts=list(HOSTS.values()))
    hosts = Hosts(network, work / "zenoh", work / "logs", args.model.resolve(), args.show_commands)
    report: dict[str, Any] = {"deadline_s": args.timeout_s, "checks": {}}
    loads: list[Load] = []
    checks = report["checks"]
    try:
        network.up()
        for host in HOSTS:
            hosts.router(host)
        for host in SERVICE_HOSTS:
            for service in SERVICES:
                hosts.service(host, service)
            hosts.gateway(host)
        started = time.monotonic()
        up = wait_for(lambda: both_hosts_serving("a") and both_hosts_serving("b"), 240, 1.0)
        report["healthy_s"] = round(time.monotonic() - started, 1) if up is not None else None
        if up is None:
            raise RuntimeError(f"not healthy: dead {hosts.dead()}, a: {health('a')}")
        load = Load(hosts, args.duration_s, args.timeout_s)
        loads.append(load)
        marks: list[tuple[str, float]] = []  # phases, each until the next one starts

        def phase(name: str) -> None:
            marks.append((name, time.time()))

        phase("baseline")
        time.sleep(10)
        # 1. Host a's services killed; host b serves everything.
        phase("services_killed")
        for service in SERVICES:
            hosts.kill(f"{service}-a")
        time.sleep(8)
        phase("services_restarting")
        for service in SERVICES:
            hosts.service("a", service)
        report["services_restarted_s"] = wait_for(lambda: both_hosts_serving("b"), 120)
        # 2. Host a's link cut, then restored.
        phase("link_cut")
        network.cut("a")
        cut_at = time.monotonic()
        report["link_left_s"] = wait_for(lambda: not any_of_host("a", "b"), args.cut_s)
        time.sleep(max(0.0, args.cut_s - (time.monotonic() - cut_at)))
        network.restore("a")
        phase("after_cut")
        report["link_rejoin_s"] = wait_for(lambda: both_hosts_serving("b"), 60)
        # 3. Host b's router killed and started again; its processes reconnect by themselves.
        phase("router_restart")
        hosts.kill("router-b")
        time.sleep(2)
        hosts.router("b")
        report["router_rejoin_s"] = wait_for(
            lambda: both_hosts_serving("a") and both_hosts_serving("b"), 60
        )
        # 4. Impostors on the robot host.
        phase("impostor")
        report["impostor"] = impostors(hosts)
        phase("steady")
        load.process.wait(args.duration_s + args.timeout_s + 60)
        load.reader.join(5)
        marks.append(("", float("inf")))
        phases = {name: (at, marks[i + 1][1]) for i, (name, at) in enumerate(marks[:-1])}
        report["all"] = summary(load.lines)
        # Queries the mesh ended unanswered, which the robot client asked again (its log).
        log_text = (work / "logs" / "load.log").read_text()
        report["all"]["asked_again"] = log_text.count("asking again")
        report["phases"] = {name: summary(load.between(*span)) for name, span in phases.items()}
        report["not_ok"] = [
            {"phase": name, "after_s": round(r["t"] - start, 2), **r}
            for name, (start, end) in phases.items()
            for r in load.between(start, end)
            if r["outcome"] != "ok"
        ]
        p = report["phases"]
        checks["no_failure_while_host_b_serves"] = all(
            p[name]["ok"] == p[name]["requests"] > 0
            for name in ("baseline", "services_killed", "services_restarting")
        )
        checks["cut_answered_within_deadline"] = (
            p["link_cut"]["requests"] > 0
            and all(r["outcome"] in ("ok", "503") for r in load.between(*phases["link_cut"]))
            and (p["link_cut"]["slowest_s"] or 0) <= args.timeout_s
        )
        checks["host_a_left_and_rejoined"] = (
            report["link_left_s"] is not None and report["link_rejoin_s"] is not None
        )
        checks["router_clients_reconnected"] = report["router_rejoin_s"] is not None
        checks["impostors_ignored"] = report["impostor"]["ok"]
        checks["served_after_faults"] = p["steady"]["ok"] == p["steady"]["requests"] > 0
        checks["every_robot_asked"] = {r["robot"] for r in load.lines} == set(ROBOTS)
        report["dead_processes"] = hosts.dead()
    finally:
        for load in loads:
            if load.process.poll() is None:
                load.process.kill()
        hosts.stop_all()
        network.down()
        report["logs"] = str(work / "logs")
        if not args.keep:
            shutil.rmtree(work / "zenoh", ignore_errors=True)
    report["passed"] = bool(checks) and all(checks.values())
    print(json.dumps(report))
    return 0 if report["passed"] else 1


def impostors(hosts: Hosts) -> dict[str, Any]:
    """Run the impostors in host c; read both gateways' /health while they are there."""
    process = subprocess.Popen(
        ["ip", "netns", "exec", hosts.network.ns(ROBOT_HOST), sys.executable, __file__,
         "impostor", "--access", str(hosts.access)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
    )  # fmt: skip
    assert process.stdout is not None
    declared = process.stdout.readline().strip() == "declared"
    time.sleep(3)  # health is asked every request: long enough for a token to be seen
    seen = instances(health("a")) | instances(health("b"))
    try:
        out, err = process.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        process.kill()
        out, err = process.communicate()
    try:
        result = json.loads(out.strip().splitlines()[-1])
    except (IndexError, ValueError):
        return {"ok": False, "error": err[-2000:]}
    result["in_health"] = sorted(i for i in seen if i.startswith("impostor"))
    result["ok"] = declared and (
        result["queries"] == 0 and not result["wrong_password_joined"] and not result["in_health"]
    )
    return result


def impostor(args: argparse.Namespace) -> int:
    """A robot's valid credentials declaring the services' keys and a planner's token, and
    answering as a planner would (so that it would show in /health if the rules let it); and a
    wrong password joining."""
    import zenoh

    from shared.bus import BusConfig, alive_key, open_session, service_key
    from shared.messages import InfoReply, pack

    endpoint = [f"tcp/127.0.0.1:{ZENOH_PORT}"]
    queries = 0
    info = InfoReply(service="planner", instance="impostor-planner", task="box_stacking",
                     model_id="impostor", image_size=64, latent_dim=12, pid=os.getpid(),
                     uptime_s=1.0)  # fmt: skip

    def answer(query: zenoh.Query) -> None:
        nonlocal queries
        queries += 1
        query.reply(query.key_expr, pack(info))

    session = open_session(
        BusConfig(
            connect=endpoint,
            open_timeout_s=10,
            config_file=args.access / f"robot-{ROBOTS[0]}.json5",
        )
    )
    keys = [service_key(s, "box_stacking", "**") for s in SERVICES]
    queryables = [session.declare_queryable(k, answer, complete=True) for k in keys]
    token = session.liveliness().declare_token(alive_key("planner", "impostor-planner"))
    print("declared", flush=True)
    wrong = json.loads((args.access / "planner.json5").read_text())
    wrong["transport"]["auth"]["usrpwd"]["password"] += "x"
    wrong_file = args.access / "wrong.json5"
    wrong_file.write_text(json.dumps(wrong))
    try:
        stranger = open_session(
            BusConfig(connect=endpoint, open_timeout_s=3, config_file=wrong_file)
        )
        joined = True
        stranger.close()
    except ConnectionError:
        joined = False
    time.sleep(args.watch_s)
    del token, queryables
    session.close()
    print(json.dumps({"queries": queries, "wrong_password_joined": joined}), flush=True)
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="mode")
    parser.add_argument("--model", type=Path, default=ROOT / "models" / "box_stacking")
    parser.add_argument("--cut-s", type=float, default=10.0)
    parser.add_argument("--duration-s", type=float, default=120.0, help="the robots' load")
    parser.add_argument("--timeout-s", type=float, default=6.0, help="a robot's deadline")
    parser.add_argument("--show-commands", action="store_true")
    parser.add_argument("--keep", action="store_true", help="keep the generated credentials")
    loader = sub.add_parser("load")
    loader.add_argument("--access", type=Path, required=True)
    loader.add_argument("--duration-s", type=float, required=True)
    loader.add_argument("--timeout-s", type=float, required=True)
    loader.add_argument("--max-requests", type=int, default=100_000)
    loader.add_argument("--pause-s", type=float, default=0.05)
    loader.add_argument("--seed", type=int, default=0)
    fake = sub.add_parser("impostor")
    fake.add_argument("--access", type=Path, required=True)
    fake.add_argument("--watch-s", type=float, default=8.0)
    args = parser.parse_args()
    if args.mode == "load":
        return load(args)
    if args.mode == "impostor":
        return impostor(args)
    return run(args)


if __name__ == "__main__":
    raise SystemExit(main())
