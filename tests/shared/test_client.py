"""PlanningClient against the real encoder, planner and APN handlers on a loopback zenoh network."""

import time

import numpy as np
import pytest

from services.apn import service as apn_service
from services.encoder import service as encoder_service
from services.planner import service as planner_service
from services.runtime import ModelInfo, ServiceContext
from services.sim.worlds import make_world
from services.stack import free_port
from shared.bus import BusConfig, Server, close_quietly, open_session, service_key
from shared.client import PlanningClient
from shared.settings import SHIPPED_MODEL, Settings
from shared.tasks import get_task


@pytest.fixture(scope="module")
def services():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(BusConfig(mode="router", listen=[endpoint]))
    session = open_session(BusConfig(connect=[endpoint], open_timeout_s=5))
    model = ModelInfo.read(SHIPPED_MODEL)
    decoded: list[int] = []  # rows each decode query asked for
    servers = []
    for name, module in (
        ("encoder", encoder_service),
        ("planner", planner_service),
        ("apn", apn_service),
    ):
        context = ServiceContext(name, "x", model, session, Settings())
        handlers = module.setup(context)
        if name == "encoder":
            decode = handlers["decode"]

            def counted(payload: bytes, decode=decode):
                reply = decode(payload)
                decoded.append(len(reply.images.numpy()))
                return reply

            handlers["decode"] = counted
        server = Server(session, name, "x")
        for operation, handler in handlers.items():
            server.serve(service_key(name, model.task, operation), handler)
        servers.append(server)
    caller = open_session(BusConfig(connect=[endpoint], open_timeout_s=5))
    time.sleep(0.3)
    yield PlanningClient(caller, model.task), decoded
    for server in servers:
        server.close()
    for s in (caller, session, router):
        close_quietly(s)


def test_plans_check_out_and_each_node_is_decoded_once(services):
    client, decoded = services
    task = get_task("box_stacking")
    rng = np.random.default_rng(3)
    states = [task.sample_state(rng) for _ in range(2)]
    with make_world("box_stacking", 64) as world:
        images = []
        for state in states:
            world.reset(state, rng)
            images.append(world.render())

    plans, reason, timings = client.plan_with_reason(images[0], images[1])
    assert plans, reason
    assert [t.operation for t in timings] == ["encode", "paths", "propose", "decode"]
    assert all(0 < t.handler_ms < t.round_trip_ms for t in timings)
    for plan in plans:
        assert len(plan.images) == len(plan.nodes) == len(plan.actions) + 1
    nodes = {n for plan in plans for n in plan.nodes}
    assert sum(decoded) == len(nodes)  # one decode query, every node on some plan once

    again, _, timings = client.plan_with_reason(images[0], images[1])
    assert [t.operation for t in timings] == ["encode", "paths", "propose"]
    assert sum(decoded) == len(nodes)  # nothing decoded the second time
    for first, second in zip(plans, again, strict=True):
        assert first.nodes == second.nodes and first.actions == second.actions
        assert all(np.array_equal(a, b) for a, b in zip(first.images, second.images, strict=True))
