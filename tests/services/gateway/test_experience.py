"""Robots report what they did, over REST and zenoh; the gateway records it for growth."""

from __future__ import annotations

import json
import time

import httpx
import numpy as np
import pytest

from shared.bus import JSON, BusConfig, Server, close_quietly, experience_key, open_session
from shared.bus import service_key as key_of
from shared.dataset import load_dataset
from shared.images import png_b64
from shared.messages import InfoReply

SIZE = 16
MOVE = {"pick": {"row": 2, "col": 0}, "release": {"row": 2, "col": 1}}


@pytest.fixture(scope="module")
def encoder_info(router_endpoint):
    """An encoder that only says its image size (the gateway records at the model's size)."""
    session = open_session(BusConfig(connect=[router_endpoint], open_timeout_s=5))
    server = Server(session, "encoder", "stub")
    info = InfoReply(
        service="encoder", instance="stub", task="box_stacking", model_id="m", image_size=SIZE,
        latent_dim=4, pid=1, uptime_s=1.0,
    )  # fmt: skip
    server.serve(key_of("encoder", "box_stacking", "info/stub"), lambda _: info, per_instance=False)
    time.sleep(0.3)
    yield
    server.close()
    close_quietly(session)


@pytest.fixture(scope="module")
def recording(gateway_with, encoder_info, tmp_path_factory):
    folder = tmp_path_factory.mktemp("experience")
    for url in gateway_with(experience_dir=folder):
        with httpx.Client(base_url=url, timeout=30) as client:
            yield client, folder


def image(value: int) -> str:
    return png_b64(np.full((SIZE, SIZE, 3), value, np.uint8))


def body(*rows: tuple[str, dict | None, str], task: str = "box_stacking") -> dict:
    return {"task": task, "tuples": [{"before": b, "action": a, "after": c} for b, a, c in rows]}


def test_reports_are_recorded_and_bad_ones_name_their_field(recording, router_endpoint):
    client, folder = recording
    ok = client.post(
        "/experience", json=body((image(10), MOVE, image(20)), (image(20), None, image(21)))
    )
    assert ok.status_code == 200 and ok.json() == {"recorded": 2, "total": 2}
    bad_action = client.post("/experience", json=body((image(1), {"pick": 3}, image(2))))
    assert bad_action.status_code == 422 and "tuples.0.action" in json.dumps(bad_action.json())
    bad_image = client.post(
        "/experience", json=body((image(1), None, image(2)), (image(1), None, "not base64!"))
    )
    assert bad_image.status_code == 422 and "tuples.1.after" in json.dumps(bad_image.json())

    robot = open_session(BusConfig(connect=[router_endpoint], open_timeout_s=5))
    try:
        time.sleep(0.3)
        payload = json.dumps(body((image(30), None, image(31))))
        replies = list(
            robot.get(experience_key("box_stacking"), payload=payload, encoding=JSON, timeout=10)
        )
        assert json.loads(replies[0].ok.payload.to_bytes()) == {"recorded": 1, "total": 3}
        replies = list(
            robot.get(experience_key("cloth_folding"), payload=payload, encoding=JSON, timeout=10)
        )
        error = json.loads(replies[0].err.payload.to_bytes())
        assert error["status"] == 422 and "task" in json.dumps(error["detail"])
    finally:
        close_quietly(robot)

    data = load_dataset(folder / "box_stacking")  # a dataset lsr roadmap grow reads
    assert len(data) == 3 and data.a.tolist() == [1, 0, 0] and data.image1.shape[1] == SIZE
    assert data.spec.state is None  # a robot does not know the true state
    assert int(data.image1[0, 0, 0, 0]) == 10 and int(data.image2[0, 0, 0, 0]) == 20


def test_without_an_experience_folder_reports_are_unavailable(gateway_with, encoder_info):
    for url in gateway_with():
        reply = httpx.post(f"{url}/experience", json=body((image(1), None, image(2))), timeout=30)
        assert reply.status_code == 503 and "LSR_EXPERIENCE_DIR" in reply.text


def test_a_robot_reports_in_batches_and_sends_the_rest_when_it_stops(recording, router_endpoint):
    from services.data.experience import has_experience
    from services.robot import REPORT_EVERY, RobotPlanner
    from shared.tasks import get_task

    _, folder = recording
    log = folder / "box_stacking"
    before = len(load_dataset(log)) if has_experience(log) else 0
    move = get_task("box_stacking").parse_action(MOVE)
    robot = open_session(BusConfig(connect=[router_endpoint], open_timeout_s=5))
    planner = RobotPlanner(robot, "r9", "box_stacking")
    try:
        time.sleep(0.3)
        still = np.full((SIZE, SIZE, 3), 40, np.uint8)
        answers = [planner.report(still, move, still + i) for i in range(REPORT_EVERY + 2)]
        assert answers[: REPORT_EVERY - 1] == [None] * (REPORT_EVERY - 1)  # kept, not sent
        assert answers[REPORT_EVERY - 1] == before + REPORT_EVERY  # one report of a batch
        assert answers[REPORT_EVERY:] == [None, None]
        assert planner.flush() == before + REPORT_EVERY + 2
        assert planner.flush() is None  # nothing left to send
    finally:
        planner.close()
        close_quietly(robot)
    data = load_dataset(folder / "box_stacking")
    assert data.a[before:].tolist() == [1] * (REPORT_EVERY + 2)
    assert [int(x[0, 0, 0]) for x in data.image2[before:]] == [40 + i for i in range(10)]
