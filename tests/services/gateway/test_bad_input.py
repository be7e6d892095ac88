"""Bad input over real HTTP: a 4xx naming the field, a short echo, never a 500 or a stall."""

from __future__ import annotations

import json
import threading
import time

import httpx
import pytest

STATE = '{"stacks": [["red"], ["green", "blue"], ["yellow"]]}'
ENDS = f'"start": {{"state": {STATE}}}, "goal": {{"state": {STATE}}}'
PLAN = '{"task": "box_stacking", ' + ENDS + "%s}"

# (route, raw JSON body, the field the reply must name)
NON_FINITE_AND_SURROGATES = [
    ("/plan", PLAN % ', "max_plans": NaN', "max_plans"),
    ("/plan", "NaN", "body"),
    ("/plan", '{"task": NaN, ' + ENDS + "}", "task"),
    ("/plan", PLAN % ', "extra": NaN', "extra"),
    ("/plan", PLAN % ', "max_plans": 1e400', "max_plans"),
    ("/render", '{"task": "box_stacking", "state": ' + STATE + ', "seed": 1e400}', "seed"),
    ("/execute", '{"task": "box_stacking", ' + ENDS + ', "seed": -Infinity}', "seed"),
    ("/plan", '{"task": "\\ud800", ' + ENDS + "}", "task"),
    ("/plan", PLAN % ', "\\udfff": 1', "body"),
    ("/plan", PLAN % ', "robot_id": "\\ud800"', "robot_id"),
    ("/plan", PLAN % ', "robot_id": "arm-\\udc00"', "robot_id"),
    ("/plan", PLAN % ', "max_plans": ' + "9" * 5000, "body"),  # past int() of a string's limit
]


def post_raw(http: httpx.Client, path: str, body: bytes | str, content_type: str) -> httpx.Response:
    return http.post(path, content=body, headers={"content-type": content_type})


@pytest.mark.parametrize(
    ("path", "body", "field"),
    NON_FINITE_AND_SURROGATES,
    ids=[f"{path} {field} {i}" for i, (path, _, field) in enumerate(NON_FINITE_AND_SURROGATES)],
)
def test_non_finite_numbers_and_lone_surrogates_get_422_naming_the_field(http, path, body, field):
    reply = post_raw(http, path, body, "application/json")
    assert reply.status_code == 422, reply.text
    detail = reply.json()["detail"]
    assert any(field in error["loc"] for error in detail), detail
    reply.content.decode("utf-8")  # strictly valid UTF-8 JSON: no lone surrogate went out


def test_bytes_that_are_not_utf8_get_a_4xx(http):
    reply = post_raw(http, "/plan", b"\xff\xfe\xfd not json", "text/plain")
    assert reply.status_code == 415 and reply.json()["detail"][0]["loc"] == [
        "header",
        "content-type",
    ]
    reply = post_raw(http, "/plan", b'{"task": "box_\xff\xfe"}', "application/json")
    assert reply.status_code == 422 and reply.json()["detail"][0]["loc"] == ["body", 14]
    reply = http.post("/plan", content=b"{}")  # no content type at all: not taken for JSON
    assert reply.status_code == 415


def test_422_echoes_only_a_short_excerpt_of_the_input(http):
    huge = "x" * 500_000
    body = PLAN % f', "robot_id": "{huge}", "unknown": "{huge}"'
    reply = post_raw(http, "/plan", body, "application/json")
    assert reply.status_code == 422
    assert len(reply.content) < 2_000, len(reply.content)  # not 1 MB back
    fields = {e["loc"][-1] for e in reply.json()["detail"]}
    assert {"robot_id", "unknown"} <= fields
    bad_state = '{"task": "box_stacking", "state": {"stacks": [["' + huge + '"], [], []]}}'
    reply = post_raw(http, "/render", bad_state, "application/json")
    assert reply.status_code == 422 and len(reply.content) < 2_000


@pytest.mark.parametrize("shape", ["wide", "deep", "long list"])
def test_a_body_asking_for_much_work_is_cut_off_early_and_stalls_nobody(http, wide_body, shape):
    body = {
        "wide": wide_body,
        "deep": b"[" * 100_000 + b"]" * 100_000,
        "long list": PLAN.encode() % (b', "max_plans": [' + b"0," * 300_000 + b"0]"),
    }[shape]
    assert len(body) < 4 * 1024 * 1024  # under the byte limit: only the structure is too much
    answers: list[tuple[int, int, float]] = []

    def send() -> None:
        started = time.monotonic()
        reply = post_raw(http, "/plan", body, "application/json")
        answers.append((reply.status_code, len(reply.content), time.monotonic() - started))

    sender = threading.Thread(target=send)
    sender.start()
    waits = []
    while sender.is_alive():
        started = time.monotonic()
        assert http.get("/tasks/box_stacking").status_code == 200
        waits.append(time.monotonic() - started)
    sender.join()
    status, size, took = answers[0]
    assert status == 422 and size < 1_000 < len(body), (status, size)
    assert took < 2.0 and max(waits, default=0) < 1.0, (took, waits)


def test_state_objects_refuse_unknown_keys(http):
    body = {"task": "box_stacking", "state": {**json.loads(STATE), "x": 1}}
    reply = http.post("/render", json=body)
    assert reply.status_code == 422 and reply.json()["detail"][0]["loc"] == [
        "body",
        "state",
        "x",
    ]


@pytest.mark.parametrize("path", ["/render", "/execute"])
def test_an_unknown_appearance_level_gets_422_naming_it(http, path):
    body = {"task": "box_stacking", "state": json.loads(STATE), "appearance": "foggy"}
    if path == "/execute":
        body = {"task": "box_stacking", **json.loads("{" + ENDS + "}"), "appearance": "foggy"}
    reply = http.post(path, json=body)
    assert reply.status_code == 422, reply.text
    (error,) = reply.json()["detail"]
    assert error["loc"] == ["body", "appearance"]
    assert "unknown appearance level 'foggy'" in error["msg"]
    assert "clean, camera, shifted" in error["msg"]
    body["appearance"] = "camera"  # a known level passes validation (no sim here to answer)
    assert http.post(path, json=body).status_code != 422
