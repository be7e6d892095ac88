"""PlanningClient against the real encoder, planner and APN handlers on a loopback zenoh network."""

import time
from functools import partial

import numpy as np
import pytest

from services.apn import service as apn_service
from services.encoder import service as encoder_service
from services.planner import service as planner_service
from services.planner.roadmap import Roadmap
from services.runtime import ModelInfo, ServiceContext, _info
from services.sim.worlds import make_world
from services.stack import free_port
from shared.bus import BusConfig, Server, close_quietly, open_session, service_key
from shared.client import PlanningClient
from shared.plans import UnknownImageError
from shared.settings import SHIPPED_MODEL, Settings
from shared.tasks import get_task


@pytest.fixture(scope="module")
def services():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(BusConfig(mode="router", listen=[endpoint]))
    session = open_session(BusConfig(connect=[endpoint], open_timeout_s=5))
    model = ModelInfo.read(SHIPPED_MODEL)
    decoded: list[int] = []  # rows each decode query asked for
    decoder_model = {"id": model.model_id}  # a test may pretend a decoder of another model
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
                return reply.model_copy(update={"model_id": decoder_model["id"]})

            handlers["decode"] = counted
        server = Server(session, name, "x")
        info = partial(_info, context, time.monotonic())  # what a client asks the image size of
        server.serve(service_key(name, model.task, "info/x"), info, per_instance=False)
        for operation, handler in handlers.items():
            server.serve(service_key(name, model.task, operation), handler)
        servers.append(server)
    caller = open_session(BusConfig(connect=[endpoint], open_timeout_s=5))
    time.sleep(0.3)
    yield caller, model.task, decoded, decoder_model
    for server in servers:
        server.close()
    for s in (caller, session, router):
        close_quietly(s)


def start_and_goal() -> list[np.ndarray]:
    task = get_task("box_stacking")
    rng = np.random.default_rng(3)
    states = [task.sample_state(rng) for _ in range(2)]
    with make_world("box_stacking", 64) as world:
        images = []
        for state in states:
            world.reset(state, rng)
            images.append(world.render())
    return images


def test_plans_check_out_and_each_node_is_decoded_once(services):
    session, task, decoded, _ = services
    client = PlanningClient(session, task)
    start, goal = start_and_goal()
    before = sum(decoded)

    plans, reason, timings, match = client.plan_with_reason(start, goal)
    assert plans, reason
    assert match is not None and match["start"].known and match["goal"].known
    assert plans[0].nodes[0] == match["start"].node and plans[0].nodes[-1] == match["goal"].node
    assert [t.operation for t in timings] == ["encode", "paths", "propose", "decode"]
    assert all(0 < t.handler_ms < t.round_trip_ms for t in timings)
    for plan in plans:
        assert len(plan.images) == len(plan.nodes) == len(plan.actions) + 1
    first = sum(decoded) - before
    assert first >= len({n for plan in plans for n in plan.nodes})  # one query, each node once

    again, _, timings, _ = client.plan_with_reason(start, goal)
    assert [t.operation for t in timings] == ["encode", "paths", "propose"]
    assert sum(decoded) - before == first  # nothing decoded the second time
    for one, other in zip(plans, again, strict=True):
        assert one.nodes == other.nodes and one.actions == other.actions
        assert all(np.array_equal(a, b) for a, b in zip(one.images, other.images, strict=True))


def test_a_frame_of_noise_is_refused_by_name_and_nothing_is_planned_from_it(services):
    session, task, _, _ = services
    client = PlanningClient(session, task)
    start, goal = start_and_goal()
    noise = np.random.default_rng(0).integers(0, 256, start.shape, dtype=np.uint8)
    plans, reason, timings, match = client.plan_with_reason(start, noise)
    assert plans == [] and reason is not None and reason.startswith("the goal image is unlike")
    assert [t.operation for t in timings] == ["encode", "paths"]  # no APN, no decoding
    assert match is not None and match["start"].known and not match["goal"].known
    assert match["goal"].score > 1
    with pytest.raises(UnknownImageError) as refused:
        client.plan(noise, goal)
    assert refused.value.end == "start"


def test_images_of_another_decoder_model_are_not_kept(services):
    session, task, decoded, decoder_model = services
    client = PlanningClient(session, task)
    start, goal = start_and_goal()
    decoder_model["id"] = "another-model"
    before = sum(decoded)
    try:
        client.plan_with_reason(start, goal)
        once = sum(decoded) - before
        client.plan_with_reason(start, goal)
        assert once > 0 and sum(decoded) - before == 2 * once  # decoded again: nothing kept
    finally:
        decoder_model["id"] = ModelInfo.read(SHIPPED_MODEL).model_id


def test_the_closed_loop_protocol_passes_what_the_loop_learned_by_name(services):
    """run_episode calls `plan(start, goal, max_plans, expect=..., avoid=...)`: the sim
    service's loop plans through this client, whose fourth parameter is `include_images`."""
    session, task, _, _ = services
    client = PlanningClient(session, task)
    start, goal = start_and_goal()
    first = client.plan(start, goal)[0]
    assert first.images == []  # plans only, unless asked
    step = tuple(first.nodes[:2])
    again = client.plan(start, goal, 8, expect=first.nodes[0], avoid=[step])
    assert again and again[0].images == []
    shipped = Roadmap.load(SHIPPED_MODEL / "roadmap")
    assert [p.nodes for p in again] == shipped.shortest_paths(
        first.nodes[0], first.nodes[-1], 8, avoid=[step]
    )
