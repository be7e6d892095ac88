"""`lsr/api/plan` over a real router: every payload gets an answer, promptly, within limits."""

from __future__ import annotations

import json
import time

import msgpack
import pytest

from shared.bus import API_PLAN_KEY, JSON, BusConfig, close_quietly, open_session

STATE = '{"stacks": [["red"], ["green", "blue"], ["yellow"]]}'
ENDS = f'"start": {{"state": {STATE}}}, "goal": {{"state": {STATE}}}'
PLAN = '{"task": "box_stacking", ' + ENDS + "%s}"


@pytest.fixture(scope="module")
def robot(live_gateway):
    session = open_session(BusConfig(connect=[live_gateway.endpoint], open_timeout_s=5))
    time.sleep(0.3)  # the gateway's queryable is known to the router
    yield session
    close_quietly(session)


def ask(session, payload: bytes) -> tuple[int, object, float, int]:
    """(status, detail, seconds until the query ended, reply bytes)."""
    started = time.monotonic()
    replies = list(session.get(API_PLAN_KEY, payload=payload, encoding=JSON, timeout=10))
    took = time.monotonic() - started
    assert len(replies) == 1, replies
    assert replies[0].err is not None
    raw = replies[0].err.payload.to_bytes()
    body = json.loads(raw)
    return body["status"], body["detail"], took, len(raw)


@pytest.mark.parametrize(
    "payload",
    [
        bytes(range(256)) * 4,  # random-looking bytes
        msgpack.packb({"task": "box_stacking"}),
        b'{"task":"box_\xff\xfe"}',
        b"",
        (PLAN % ', "max_plans": NaN').encode(),
        (PLAN % ', "robot_id": "\\ud800"').encode(),
    ],
    ids=["bytes", "msgpack", "not UTF-8", "empty", "NaN", "lone surrogate"],
)
def test_payloads_that_are_not_a_plan_request_get_a_4xx_reply_at_once(robot, payload):
    status, detail, took, _ = ask(robot, payload)
    assert 400 <= status < 500, detail
    assert took < 1.0, took


def test_a_payload_of_many_keys_is_cut_off_early_with_a_small_reply(robot, wide_body):
    status, detail, took, size = ask(robot, wide_body)
    assert status == 422 and "items" in json.dumps(detail)
    assert took < 1.0 and size < 1_000, (took, size)


def test_payloads_over_the_size_limit_get_413(robot, live_gateway):
    limit = live_gateway.settings.max_body_bytes
    status, detail, _, _ = ask(robot, b'"' + b"x" * limit + b'"')
    assert status == 413 and str(limit) in json.dumps(detail)
