"""Access control on a real router loaded from the generated files: only the services serve."""

from __future__ import annotations

import json
import shutil
import time

import numpy as np
import pytest
import zenoh

from services.stack import free_port
from shared.bus import (
    API_PLAN_KEY,
    JSON,
    BusConfig,
    Replicas,
    Server,
    ServiceUnavailable,
    call,
    close_quietly,
    open_session,
    progress_key,
    robot_plan_key,
    service_key,
)
from shared.messages import DecodeReply, DecodeRequest, WireArray, pack, unpack
from shared.zenoh_access import write_deployment


@pytest.fixture(scope="module")
def deployment(tmp_path_factory):
    paths = write_deployment(tmp_path_factory.mktemp("zenoh"), robots=["arm-1", "arm-2"])
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(BusConfig(mode="router", listen=[endpoint], config_file=paths["router"]))
    sessions: list[zenoh.Session] = []

    def join(role: str | None) -> zenoh.Session:
        config = BusConfig(connect=[endpoint], open_timeout_s=2, config_file=paths.get(role))
        sessions.append(open_session(config))
        return sessions[-1]

    yield paths, endpoint, join
    for session in [*sessions, router]:
        close_quietly(session)


def answer_as(name: str):
    def decode(_: bytes) -> DecodeReply:
        return DecodeReply(images=WireArray.of(np.full((1, 1, 1, 3), ord(name[0]), np.uint8)))

    return decode


def test_the_files_hold_secrets_readable_by_their_owner_only(deployment):
    paths, _, _ = deployment
    assert (paths["router"].parent / "users.txt").stat().st_mode & 0o077 == 0
    assert paths["planner"].stat().st_mode & 0o077 == 0
    assert "access_control" in json.loads(paths["router"].read_text())


def test_strangers_cannot_join(deployment):
    paths, endpoint, join = deployment
    with pytest.raises(ConnectionError):
        join(None)  # no credentials
    wrong = paths["planner"].with_name("wrong.json5")
    wrong.write_text(
        json.dumps({"transport": {"auth": {"usrpwd": {"user": "planner", "password": "x"}}}})
    )
    with pytest.raises(ConnectionError):
        open_session(BusConfig(connect=[endpoint], open_timeout_s=1, config_file=wrong))


def test_an_impostor_planner_gets_no_query_and_its_token_is_not_seen(deployment):
    _, _, join = deployment
    real = Server(join("planner"), "planner", "real")
    real.serve(service_key("planner", "t", "paths"), answer_as("real"))
    impostors = [Server(join(role), "planner", f"fake-{role}") for role in ("robot-arm-1", "apn")]
    for impostor in impostors:  # a robot, and another service, each trying to serve plans
        impostor.serve(service_key("planner", "t", "paths"), answer_as("fake"))
    gateway = join("gateway")
    replicas = Replicas(gateway)
    time.sleep(0.5)
    assert replicas._alive.get("planner") == ["real"]  # the impostors' tokens never arrived
    z = DecodeRequest(task="t", latents=WireArray.of(np.zeros((1, 2), np.float32)))
    answers = {
        chr(
            call(gateway, "planner", "t", "paths", z, DecodeReply, 2.0, replicas=replicas)
            .result()
            .images.numpy()[0, 0, 0, 0]
        )
        for _ in range(10)
    }
    assert answers == {"r"}
    every = gateway.get(
        service_key("planner", "t", "paths/**"),
        payload=pack(z),
        target=zenoh.QueryTarget.ALL,
        consolidation=zenoh.ConsolidationMode.NONE,
        timeout=1,
    )
    served = [unpack(r.ok.payload.to_bytes(), DecodeReply) for r in every if r.ok is not None]
    assert served and {chr(d.images.numpy()[0, 0, 0, 0]) for d in served} == {"r"}
    # A robot may not ask the planner directly.
    with pytest.raises(ServiceUnavailable):
        call(join("robot-arm-2"), "planner", "t", "paths", z, DecodeReply, 1.0).result()
    real.close()


def test_robots_use_the_api_and_read_only_their_own_plans(deployment):
    _, _, join = deployment
    gateway = join("gateway")
    queryable = gateway.declare_queryable(
        API_PLAN_KEY, lambda q: q.reply(q.key_expr, b'{"plans": []}', encoding=JSON), complete=True
    )
    arm1, arm2, forger = join("robot-arm-1"), join("robot-arm-2"), join("robot-arm-2")
    mine: list[bytes] = []
    theirs: list[bytes] = []
    arm1.declare_subscriber(robot_plan_key("arm-1"), lambda s: mine.append(s.payload.to_bytes()))
    arm2.declare_subscriber(robot_plan_key("arm-1"), lambda s: theirs.append(s.payload.to_bytes()))
    time.sleep(0.5)
    replies = list(arm1.get(API_PLAN_KEY, payload=b"{}", timeout=2))
    assert [r.ok.payload.to_bytes() for r in replies if r.ok] == [b'{"plans": []}']
    gateway.put(robot_plan_key("arm-1"), b"plan for arm-1")
    forger.put(robot_plan_key("arm-1"), b"forged by arm-2")  # robots may not publish plans
    time.sleep(0.5)
    assert mine == [b"plan for arm-1"] and theirs == []
    queryable.undeclare()


def test_only_the_sim_publishes_episode_steps_and_only_the_gateway_reads_them(deployment):
    _, _, join = deployment
    key = progress_key("t", "0" * 32)
    gateway, robot, monitor = join("gateway"), join("robot-arm-1"), join("monitor")
    heard: dict[str, list[bytes]] = {"gateway": [], "robot": [], "monitor": []}
    for name, session in (("gateway", gateway), ("robot", robot), ("monitor", monitor)):
        session.declare_subscriber(key, lambda s, n=name: heard[n].append(s.payload.to_bytes()))
    time.sleep(0.5)
    join("sim").put(key, b"step 1")
    join("planner").put(key, b"forged by the planner")  # another service may not
    time.sleep(0.5)
    assert heard == {"gateway": [b"step 1"], "robot": [], "monitor": []}


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command")
def test_tls_links_admit_only_processes_that_trust_the_deployments_ca(tmp_path):
    paths = write_deployment(tmp_path, robots=[], tls_hosts=["localhost", "127.0.0.1"])
    port = free_port()
    router = open_session(
        BusConfig(mode="router", listen=[f"tls/127.0.0.1:{port}"], config_file=paths["router"])
    )
    sessions = []
    try:

        def join(role: str, endpoint: str = f"tls/localhost:{port}") -> zenoh.Session:
            config = BusConfig(connect=[endpoint], open_timeout_s=2, config_file=paths[role])
            sessions.append(open_session(config))
            return sessions[-1]

        server = Server(join("planner"), "planner", "real")
        server.serve(service_key("planner", "t", "paths"), answer_as("real"))
        gateway = join("gateway")
        time.sleep(0.3)
        z = DecodeRequest(task="t", latents=WireArray.of(np.zeros((1, 2), np.float32)))
        reply = call(gateway, "planner", "t", "paths", z, DecodeReply, 2.0).result()
        assert chr(reply.images.numpy()[0, 0, 0, 0]) == "r"  # served over TLS
        server.close()
        untrusting = json.loads(paths["monitor"].read_text())
        del untrusting["transport"]["link"]  # right password, but no CA to check the router by
        no_ca = tmp_path / "no-ca.json5"
        no_ca.write_text(json.dumps(untrusting))
        with pytest.raises(ConnectionError):
            open_session(
                BusConfig(connect=[f"tls/localhost:{port}"], open_timeout_s=1, config_file=no_ca)
            )
        with pytest.raises(ConnectionError):  # plain TCP: nothing listens
            join("monitor", f"tcp/127.0.0.1:{port}")
    finally:
        for session in [*sessions, router]:
            close_quietly(session)


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command")
def test_routers_mesh_over_tls_and_apply_the_rules_to_their_own_processes(tmp_path):
    """Two routers (two sites) meshed over TLS with the same files: a planner on one serves a
    gateway on the other; a robot on the other still may not ask it, nor serve in its name.
    The many-host run with faults is benchmarks/mesh_faults.py."""
    paths = write_deployment(tmp_path, robots=["arm-1"], tls_hosts=["127.0.0.1"])
    first, second = free_port(), free_port()
    routers = [
        open_session(
            BusConfig(
                mode="router",
                listen=[f"tls/127.0.0.1:{port}"],
                connect=peers,
                config_file=paths["router"],
            )
        )
        for port, peers in ((first, []), (second, [f"tls/127.0.0.1:{first}"]))
    ]
    sessions = []
    try:

        def join(role: str, port: int) -> zenoh.Session:
            config = BusConfig(
                connect=[f"tls/127.0.0.1:{port}"], open_timeout_s=2, config_file=paths[role]
            )
            sessions.append(open_session(config))
            return sessions[-1]

        server = Server(join("planner", first), "planner", "real")
        server.serve(service_key("planner", "t", "paths"), answer_as("real"))
        robot = join("robot-arm-1", second)
        impostor = Server(join("robot-arm-1", second), "planner", "impostor")
        impostor.serve(service_key("planner", "t", "paths"), answer_as("impostor"))
        gateway = join("gateway", second)
        time.sleep(0.5)
        z = DecodeRequest(task="t", latents=WireArray.of(np.zeros((1, 2), np.float32)))
        for _ in range(4):  # across the mesh, and never from the impostor
            reply = call(gateway, "planner", "t", "paths", z, DecodeReply, 2.0).result()
            assert chr(reply.images.numpy()[0, 0, 0, 0]) == "r"
        with pytest.raises(ServiceUnavailable):
            call(robot, "planner", "t", "paths", z, DecodeReply, 0.5).result()
        server.close()
        impostor.close()
    finally:
        for session in [*sessions, *routers]:
            close_quietly(session)
