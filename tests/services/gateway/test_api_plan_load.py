"""`lsr/api/plan` under load, over a real router: it sheds what would queue past its limit.

Its own module: gateways of other modules' fixtures would share the queries.
"""

from __future__ import annotations

import json
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from shared.bus import API_PLAN_KEY, JSON, BusConfig, close_quietly, open_session

DEADLINE_S = 1.0
STATE = {"stacks": [["red"], ["green", "blue"], ["yellow"]]}
PLAN = {"task": "box_stacking", "start": {"state": STATE}, "goal": {"state": STATE}}


@pytest.fixture(scope="module")
def one_queued_gateway(gateway_with, slow_services):
    yield from gateway_with(deadline_s=DEADLINE_S, max_queued=1)


def test_lsr_api_plan_sheds_what_would_queue_past_its_limit(one_queued_gateway, router_endpoint):
    session = open_session(BusConfig(connect=[router_endpoint], open_timeout_s=5))
    try:
        time.sleep(0.3)
        payload = json.dumps(PLAN)

        def ask(_: int) -> tuple[int, float]:
            started = time.monotonic()
            replies = list(session.get(API_PLAN_KEY, payload=payload, encoding=JSON, timeout=10))
            status = json.loads(replies[0].err.payload.to_bytes())["status"]
            return status, time.monotonic() - started

        with ThreadPoolExecutor(8) as pool:
            answers = list(pool.map(ask, range(8)))
    finally:
        close_quietly(session)
    assert all(status == 503 for status, _ in answers), answers  # the planner hangs
    quick = [took for _, took in answers if took < 0.3]
    # 4 workers and 1 queued take the deadline; the other 3 are refused at once
    assert len(quick) >= 3, answers
