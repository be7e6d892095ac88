"""Which tasks a deployment serves: listed by GET /tasks; a known task that nobody serves gets
404 naming it at once, over REST and over zenoh, never a 503 after the deadline."""

import json
import time

import pytest

from shared.bus import API_PLAN_KEY, BusConfig, close_quietly, open_session

CLOTH = {"folds": ["top_left"]}


def test_get_tasks_lists_the_served_tasks(http):
    assert http.get("/tasks").json() == {"tasks": ["box_stacking"]}
    info = http.get("/tasks/cloth_folding").json()  # described even where it is not served
    assert info["num_states"] == 16 and info["spec"]["action"]["dtype"] == "int16"


@pytest.mark.parametrize(
    ("route", "body"),
    [
        ("/plan", {"task": "cloth_folding", "start": {"state": CLOTH}, "goal": {"state": CLOTH}}),
        ("/render", {"task": "cloth_folding", "state": CLOTH, "seed": 0}),
        (
            "/execute",
            {"task": "cloth_folding", "start": {"state": CLOTH}, "goal": {"state": CLOTH}},
        ),
    ],
)
def test_a_task_nobody_serves_gets_404_at_once(http, route, body):
    started = time.monotonic()
    reply = http.post(route, json=body)
    assert reply.status_code == 404, reply.text
    assert "'cloth_folding' is not served here" in reply.json()["detail"]
    assert "box_stacking" in reply.json()["detail"]
    assert time.monotonic() - started < 0.5


def test_an_unknown_task_still_names_the_known_ones(http):
    reply = http.post("/render", json={"task": "origami", "state": CLOTH, "seed": 0})
    assert reply.status_code == 422 and "cloth_folding" in json.dumps(reply.json())


def test_the_zenoh_api_says_404_too(live_gateway):
    session = open_session(BusConfig(connect=[live_gateway.endpoint], open_timeout_s=5))
    try:
        body = {"task": "cloth_folding", "start": {"state": CLOTH}, "goal": {"state": CLOTH}}
        deadline = time.monotonic() + 5
        replies = []
        while not replies and time.monotonic() < deadline:  # until the queryable is seen
            replies = list(session.get(API_PLAN_KEY, payload=json.dumps(body), timeout=2.0))
        error = json.loads(replies[0].err.payload.to_bytes())
        assert error["status"] == 404 and "not served" in error["detail"]
    finally:
        close_quietly(session)
