"""The robot client over a real loopback zenoh network, with a stand-in gateway."""

import json

import pytest
import zenoh

from services.robot import RobotPlanner
from services.stack import free_port
from shared.bus import (
    API_PLAN_KEY,
    JSON,
    BusConfig,
    ServiceUnavailable,
    close_quietly,
    open_session,
)


@pytest.fixture
def bus():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(BusConfig(mode="router", listen=[endpoint]))
    sessions = [open_session(BusConfig(connect=[endpoint], open_timeout_s=5)) for _ in range(2)]
    yield sessions
    for session in [*sessions, router]:
        close_quietly(session)


def test_a_query_the_network_ends_unanswered_is_asked_again(bus):
    gateway, robot = bus
    asked = []

    def answer(query: zenoh.Query) -> None:
        asked.append(json.loads(query.payload.to_bytes())["robot_id"])
        if len(asked) > 1:  # the first is dropped unanswered, as a mesh does while routes change
            query.reply(API_PLAN_KEY, json.dumps({"plan_id": "p-1"}), encoding=JSON)

    queryable = gateway.declare_queryable(API_PLAN_KEY, answer, complete=True)
    planner = RobotPlanner(robot, "arm-1", "box_stacking", timeout_s=3.0)
    assert planner._request({"robot_id": "arm-1"}) == "p-1"
    assert asked == ["arm-1", "arm-1"]
    queryable.undeclare()


def test_no_gateway_at_all_is_unavailable_within_the_timeout(bus):
    _, robot = bus
    planner = RobotPlanner(robot, "arm-1", "box_stacking", timeout_s=0.6)
    with pytest.raises(ServiceUnavailable, match="no answer"):
        planner._request({"robot_id": "arm-1"})
