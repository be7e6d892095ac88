"""End to end: the real router, services and gateway as processes on free loopback ports.

The stack serves the shipped models (box stacking, cloth and T-shirt folding, rope-box), four
services each.
Tests run in file order; the ones that stop or kill processes come last.
"""

from __future__ import annotations

import base64
import io
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image

from services.planner.evaluate import TransitionChecker
from services.sim.workcell import FRAME_SIZE
from services.stack import Stack, StackConfig, check_ports_free, free_port
from shared.bus import (
    API_PLAN_KEY,
    JSON,
    BusConfig,
    Server,
    close_quietly,
    open_session,
    service_key,
)
from shared.dataset import load_dataset
from shared.messages import PathsReply, WireArray
from shared.tasks import get_task
from shared.zenoh_access import write_deployment

MODEL = Path(__file__).resolve().parents[2] / "models" / "box_stacking"
CLOTH_MODEL = MODEL.parent / "cloth_folding"
TASK = get_task("box_stacking")
CLOTH = get_task("cloth_folding")
CLOTH_START = {"folds": ["top_left", "bottom_right"]}
CLOTH_GOAL = {"folds": ["top_right", "bottom_right"]}
CLOTH_GOOD = {"task": "cloth_folding", "start": {"state": CLOTH_START},
              "goal": {"state": CLOTH_GOAL}}  # fmt: skip
SHIRT_MODEL = MODEL.parent / "tshirt_folding"
SHIRT = get_task("tshirt_folding")
# The goal's left sleeve lies under its folded side and the folded half: no camera above sees
# whether it is folded, so plans and the closed loop are judged by the goal's view.
SHIRT_HIDDEN = {"folds": ["left_sleeve", "left_side", "bottom_half"]}
ROPE_MODEL = MODEL.parent / "rope_box"
ROPE = get_task("rope_box")
ROPE_START = {
    "boxes": {"green": {"row": 0, "col": 0}, "orange": {"row": 0, "col": 1}},
    "rope": None,
}
# Two moves of both kinds: the rope lifted over the top-left pillar, then green pushed down.
ROPE_GOAL = {
    "boxes": {"green": {"row": 1, "col": 0}, "orange": {"row": 0, "col": 1}},
    "rope": {"pillar": {"row": 0, "col": 0}, "turn": "left"},
}
ROPE_GOOD = {"task": "rope_box", "start": {"state": ROPE_START}, "goal": {"state": ROPE_GOAL}}
SERVED = ("box_stacking", "cloth_folding", "rope_box", "tshirt_folding")
START = {"stacks": [["red", "green"], ["blue"], ["yellow"]]}
GOAL = {"stacks": [[], ["yellow", "green", "red"], ["blue"]]}
GOOD = {"task": "box_stacking", "start": {"state": START}, "goal": {"state": GOAL}}


@pytest.fixture(scope="module")
def access(tmp_path_factory) -> Path:
    """The bus runs under access control, as deployed: every process has its credentials."""
    folder = tmp_path_factory.mktemp("zenoh-access")
    write_deployment(folder, robots=["r2"])
    return folder


def as_role(access: Path, role: str) -> dict[str, str]:
    """The environment of a process that joins the bus as `role`."""
    return {**os.environ, "LSR_ZENOH_CONFIG": str(access / f"{role}.json5")}


@pytest.fixture(scope="module")
def stack(tmp_path_factory, access, patient):
    config = StackConfig(
        port=free_port(),
        zenoh_port=free_port(),
        models=(MODEL, CLOTH_MODEL, SHIRT_MODEL, ROPE_MODEL),
        log_dir=tmp_path_factory.mktemp("stack-logs"),
        zenoh_access=access,
        env={**patient, "LSR_EXPERIENCE_DIR": str(tmp_path_factory.mktemp("experience"))},
    )
    with Stack(config) as running:
        running.start()
        running.wait_healthy(90)
        yield running


@pytest.fixture(scope="module")
def http(stack):
    with httpx.Client(base_url=stack.config.url, timeout=30) as client:
        yield client


@pytest.fixture(scope="module")
def bus(stack, access):
    config = BusConfig(
        connect=[stack.config.endpoint], open_timeout_s=10, config_file=access / "monitor.json5"
    )
    session = open_session(config)
    yield session
    close_quietly(session)


def render(http: httpx.Client, state: dict, seed: int = 0) -> str:
    reply = http.post("/render", json={"task": "box_stacking", "state": state, "seed": seed})
    assert reply.status_code == 200, reply.text
    return reply.json()["image"]


def assert_plans_lead_from(
    start: dict, goal: dict, body: dict, images: bool = True, task=TASK
) -> None:
    """Every plan is legal move by move from start and ends at goal, per the task's rules,
    judged by views (interface.md): from some state looking like the start, ending in one that
    looks like the goal (the states themselves where nothing hides)."""
    assert body["plans"], body
    checker = TransitionChecker(task)
    for plan in body["plans"]:
        actions = [task.parse_action(a) for a in plan["actions"]]
        assert checker.reaches(task.parse_state(start), actions, task.parse_state(goal)), plan
        assert len(plan["nodes"]) == len(plan["actions"]) + 1
        assert len(plan["supports"]) == len(plan["actions"])
        assert all(w >= 1 for w in plan["supports"])
        assert plan["support"] == pytest.approx(
            np.prod([(w + 1) / (w + 2) for w in plan["supports"]]), abs=1e-6
        )
        if images:
            assert len(plan["images"]) == len(plan["actions"]) + 1
            first = Image.open(io.BytesIO(base64.b64decode(plan["images"][0])))
            assert first.format == "PNG" and first.size == (64, 64)


def test_health_lists_every_service_and_the_tokens_are_alive(stack, http, bus):
    reply = http.get("/health")
    assert reply.status_code == 200
    services = reply.json()["services"]
    assert set(services) == {"encoder", "planner", "apn", "sim"}
    for service in services.values():  # one instance per task
        assert service["status"] == "ok"
        assert sorted(i["task"] for i in service["instances"]) == list(SERVED)
    assert http.get("/tasks").json() == {"tasks": [m.name for m in stack.config.models]}
    tokens = {str(r.ok.key_expr).split("/")[2] for r in bus.liveliness().get("lsr/alive/**")}
    assert tokens == {"encoder", "planner", "apn", "sim", "gateway"}
    assert http.get("/tasks/box_stacking").json()["num_states"] == 288
    assert http.get("/tasks/tshirt_folding").json()["num_views"] == 25
    assert http.get("/tasks/nope").status_code == 404
    assert http.get("/docs").status_code == 200


def test_ping_is_a_health_check_for_the_instances_of_this_host(stack, access):
    def ping(*args: str, endpoint: str = stack.config.endpoint) -> subprocess.CompletedProcess:
        command = [sys.executable, "-m", "services.cli", "ping", *args, "--connect", endpoint]
        env = as_role(access, "planner")  # as in its container: the service's own credentials
        return subprocess.run(command, capture_output=True, text=True, timeout=60, env=env)

    here = ping("planner", "--this-host")
    assert here.returncode == 0 and "planner" in here.stdout, here.stderr
    nowhere = ping("planner", "--timeout", "0.5", endpoint=f"tcp/127.0.0.1:{free_port()}")
    assert nowhere.returncode == 1 and "no zenoh router" in nowhere.stderr


def test_plan_from_states(http):
    reply = http.post("/plan", json={**GOOD, "max_plans": 3})
    assert reply.status_code == 200, reply.text
    body = reply.json()
    assert len(body["plans"]) <= 3 and body["reason"] is None
    assert_plans_lead_from(START, GOAL, body)
    timing = dict(m.split(";dur=") for m in reply.headers["server-timing"].split(", "))
    assert {"encode", "encode-handler", "paths", "propose", "gateway"} <= timing.keys()
    assert float(timing["encode-handler"]) < float(timing["encode"]) < float(timing["gateway"])


def test_plan_from_images(http):
    start, goal = render(http, START, seed=5), render(http, GOAL, seed=6)
    reply = http.post(
        "/plan",
        json={
            "task": "box_stacking",
            "start": {"image": start},
            "goal": {"image": "data:image/png;base64," + goal},
        },
    )
    assert reply.status_code == 200, reply.text
    assert_plans_lead_from(START, GOAL, reply.json())


def test_zenoh_query_and_robot_publication(bus):
    received: list[dict] = []
    subscriber = bus.declare_subscriber(
        "lsr/robot/arm 7.ü/plan", lambda s: received.append(json.loads(s.payload.to_bytes()))
    )
    time.sleep(0.3)
    request = {**GOOD, "robot_id": "arm 7.ü", "include_images": False}  # any one key chunk
    replies = list(bus.get(API_PLAN_KEY, payload=json.dumps(request), encoding=JSON, timeout=10))
    assert len(replies) == 1 and replies[0].ok is not None
    assert str(replies[0].ok.encoding) == "application/json"
    body = json.loads(replies[0].ok.payload.to_bytes())
    assert_plans_lead_from(START, GOAL, body, images=False)
    deadline = time.monotonic() + 5
    while not received and time.monotonic() < deadline:
        time.sleep(0.05)
    subscriber.undeclare()
    assert received and received[0] == body  # the same JSON, for the same plan_id

    bad = list(bus.get(API_PLAN_KEY, payload=b"{not json", encoding=JSON, timeout=10))
    assert bad[0].err is not None and json.loads(bad[0].err.payload.to_bytes())["status"] == 422


@pytest.mark.parametrize(
    ("task", "start", "goal"),
    [(CLOTH, CLOTH_START, CLOTH_GOAL), (ROPE, ROPE_START, ROPE_GOAL)],
    ids=["cloth", "rope_box"],
)
def test_plans_are_legal_from_states_and_from_rendered_images(http, task, start, goal):
    ends = {"start": {"state": start}, "goal": {"state": goal}}
    reply = http.post("/plan", json={"task": task.name, **ends, "max_plans": 4})
    assert reply.status_code == 200, reply.text
    assert_plans_lead_from(start, goal, reply.json(), task=task)
    first, last = (
        http.post("/render", json={"task": task.name, "state": s, "seed": 9}).json()["image"]
        for s in (start, goal)
    )
    from_images = {"task": task.name, "start": {"image": first}, "goal": {"image": last}}
    reply = http.post("/plan", json=from_images)
    assert reply.status_code == 200, reply.text
    assert_plans_lead_from(start, goal, reply.json(), task=task)


def test_cloth_execute_reaches_its_goal(http):
    reply = http.post("/execute", json={**CLOTH_GOOD, "seed": 4})
    assert reply.status_code == 200, reply.text
    body = reply.json()
    assert body["success"] and CLOTH.parse_state(body["final_state"]) == CLOTH.parse_state(
        CLOTH_GOAL
    )
    assert len(body["steps"]) == 2  # unfold top_left, fold top_right (either order)
    assert all(set(step["action"]) == {"pick", "release", "height"} for step in body["steps"])


@pytest.mark.parametrize(
    ("start", "goal"),
    [
        ({"folds": ["right_sleeve"]}, SHIRT_HIDDEN),  # to a hidden sleeve
        (SHIRT_HIDDEN, {"folds": ["left_sleeve", "left_side"]}),  # from one: it shows again
    ],
)
def test_tshirt_plans_are_right_by_what_the_camera_shows(http, start, goal):
    body = {"task": "tshirt_folding", "start": {"state": start}, "goal": {"state": goal}}
    reply = http.post("/plan", json={**body, "max_plans": 4})
    assert reply.status_code == 200, reply.text
    plans = reply.json()["plans"]
    assert plans and all(len(p["nodes"]) == len(p["actions"]) + 1 for p in plans)
    checker = TransitionChecker(SHIRT)
    ends = SHIRT.parse_state(start), SHIRT.parse_state(goal)
    actions = [[SHIRT.parse_action(a) for a in p["actions"]] for p in plans]
    assert all(checker.reaches(ends[0], a, ends[1]) for a in actions), plans


def test_tshirt_execute_reaches_a_goal_whose_sleeve_is_hidden(http):
    body = {"task": "tshirt_folding", "start": {"state": {"folds": []}}, "seed": 5}
    reply = http.post("/execute", json={**body, "goal": {"state": SHIRT_HIDDEN}})
    assert reply.status_code == 200, reply.text
    result = reply.json()
    assert result["success"] and result["reason"] == "goal", result["reason"]
    hidden = SHIRT.parse_state(SHIRT_HIDDEN)
    assert result["final_view"] == SHIRT.view_to_json(hidden)  # the sleeve: either way
    assert SHIRT.view(SHIRT.parse_state(result["final_state"])) == SHIRT.view(hidden)
    assert 2 <= len(result["steps"]) <= 4  # fewest: the left side, then the half


def test_rope_box_execute_reaches_its_goal(http):
    reply = http.post("/execute", json={**ROPE_GOOD, "seed": 6})
    assert reply.status_code == 200, reply.text
    body = reply.json()
    assert body["success"] and body["reason"] == "goal", body["reason"]
    assert ROPE.parse_state(body["final_state"]) == ROPE.parse_state(ROPE_GOAL)
    assert sorted(step["action"]["kind"] for step in body["steps"]) == ["box", "rope"]


@pytest.mark.parametrize(
    ("body", "field", "message"),
    [
        ({**CLOTH_GOOD, "start": {"state": {"folds": ["top_left", "top_left"]}}}, "start",
         "appears twice"),
        ({**CLOTH_GOOD, "goal": {"state": {"folds": ["middle"]}}}, "goal", "unknown fold"),
        ({**CLOTH_GOOD, "start": {"state": START}}, "start", "'folds'"),
    ],
)  # fmt: skip
def test_invalid_cloth_states_name_their_field(http, body, field, message):
    reply = http.post("/plan", json=body)
    assert reply.status_code == 422, reply.text
    assert field in reply.text and message in reply.text


def noise_png(seed: int) -> str:
    pixels = np.random.default_rng(seed).integers(0, 256, (64, 64, 3), dtype=np.uint8)
    buffer = io.BytesIO()
    Image.fromarray(pixels).save(buffer, format="PNG")
    return base64.b64encode(buffer.getvalue()).decode()


@pytest.mark.parametrize("end", ["start", "goal"])
def test_an_image_unlike_the_model_s_gets_no_plan_and_the_reason_names_its_end(http, end):
    body = {**GOOD, end: {"image": noise_png(1)}}
    reply = http.post("/plan", json=body)
    assert reply.status_code == 200, reply.text
    result = reply.json()
    other = "goal" if end == "start" else "start"
    assert result["plans"] == [] and result["reason"].startswith(f"the {end} image is unlike")
    assert not result["match"][end]["known"] and result["match"][end]["score"] > 1
    assert result["match"][other]["known"] and result["match"][other]["score"] <= 1


def test_every_plan_reply_says_how_well_the_model_knows_both_ends(http):
    result = http.post("/plan", json=GOOD).json()
    assert result["plans"] and result["reason"] is None
    for end in ("start", "goal"):
        assert result["match"][end]["known"] and 0 <= result["match"][end]["score"] <= 1
    assert {p["nodes"][0] for p in result["plans"]} == {result["match"]["start"]["node"]}


def test_the_closed_loop_stops_before_acting_towards_a_goal_it_does_not_know(http):
    reply = http.post("/execute", json={**GOOD, "goal": {"image": noise_png(2)}})
    assert reply.status_code == 200, reply.text
    result = reply.json()
    assert not result["success"] and result["reason"] == "unknown_goal"
    assert result["steps"] == [] and result["detail"].startswith("the goal image is unlike")


def frame(http: httpx.Client, state: dict, seed: int = 0, task: str = "box_stacking") -> str:
    """What the cell's camera sees of `state`: the whole frame, markers and all."""
    body = {"task": task, "state": state, "seed": seed, "frame": True}
    reply = http.post("/render", json=body)
    assert reply.status_code == 200, reply.text
    return reply.json()["image"]


NEAR = slice(FRAME_SIZE // 2, FRAME_SIZE)  # rows of box stacking's markers, all near the camera
FAR = slice(0, FRAME_SIZE * 3 // 8)  # rows of the cloth's two far markers


def covered(image_b64: str, rows: slice) -> str:
    """The frame with a band of it painted over, as a sleeve or a hand would."""
    pixels = np.array(Image.open(io.BytesIO(base64.b64decode(image_b64))))
    pixels[rows] = 128
    buffer = io.BytesIO()
    Image.fromarray(pixels).save(buffer, format="PNG")
    return base64.b64encode(buffer.getvalue()).decode()


def test_a_camera_frame_is_registered_to_the_table_frame_and_planned(http):
    start, goal = frame(http, START, seed=5), frame(http, GOAL, seed=6)
    assert Image.open(io.BytesIO(base64.b64decode(start))).size == (FRAME_SIZE, FRAME_SIZE)
    reply = http.post(
        "/plan", json={"task": "box_stacking", "start": {"image": start}, "goal": {"image": goal}}
    )
    assert reply.status_code == 200, reply.text
    assert_plans_lead_from(START, GOAL, reply.json())  # plan images in the table frame, 64 px
    start, goal = (frame(http, s, 9, "cloth_folding") for s in (CLOTH_START, CLOTH_GOAL))
    from_frames = {"task": "cloth_folding", "start": {"image": start}, "goal": {"image": goal}}
    reply = http.post("/plan", json=from_frames)
    assert reply.status_code == 200, reply.text
    assert_plans_lead_from(CLOTH_START, CLOTH_GOAL, reply.json(), task=CLOTH)


@pytest.mark.parametrize("end", ["start", "goal"])
def test_a_frame_whose_markers_are_covered_is_not_known_and_the_reason_says_so(http, end):
    shown = covered(frame(http, START if end == "start" else GOAL, seed=3), NEAR)
    body = {**GOOD, end: {"image": shown}}
    result = http.post("/plan", json=body).json()
    assert result["plans"] == [] and not result["match"][end]["known"]
    assert result["reason"].startswith(f"the {end} image is not known: the table markers were not")
    assert "missing ids" in result["reason"]


def test_reported_frames_are_registered_and_one_without_markers_is_refused_by_field(http):
    shown = frame(http, CLOTH_START, seed=4, task="cloth_folding")  # box: the robot's folder
    row = {"before": shown, "action": None, "after": shown}
    reply = http.post("/experience", json={"task": "cloth_folding", "tuples": [row]})
    assert reply.status_code == 200, reply.text
    row["after"] = covered(shown, FAR)
    reply = http.post("/experience", json={"task": "cloth_folding", "tuples": [row]})
    assert reply.status_code == 422 and "tuples.0.after" in reply.text
    assert "table markers were not found" in reply.text


def test_execute_reaches_a_goal_given_as_a_camera_frame(http):
    body = {**GOOD, "goal": {"image": frame(http, GOAL, seed=8)}, "seed": 2}
    reply = http.post("/execute", json=body)
    assert reply.status_code == 200, reply.text
    assert reply.json()["success"], reply.json()["reason"]
    body["goal"] = {"image": covered(frame(http, GOAL, seed=8), NEAR)}
    result = http.post("/execute", json=body).json()
    assert result["reason"] == "unknown_goal" and result["steps"] == []
    assert "table markers were not found" in result["detail"]


def test_plan_from_a_state_to_itself_has_no_action(http):
    reply = http.post(
        "/plan",
        json={**GOOD, "goal": {"state": START}, "include_images": False},
    )
    assert reply.status_code == 200
    plans = reply.json()["plans"]
    assert plans and all(p["actions"] == [] and len(p["nodes"]) == 1 for p in plans)


def image_of(size: tuple[int, int], mode: str = "RGB", fmt: str = "PNG") -> str:
    buffer = io.BytesIO()
    Image.new(mode, size).save(buffer, format=fmt)
    return base64.b64encode(buffer.getvalue()).decode()


BAD_INPUTS = [
    ("malformed JSON", b'{"task": "box_stacking",', 422, None),
    ("not an object", [1, 2], 422, None),
    ("unknown task", {**GOOD, "task": "juggling"}, 422, "task"),
    ("missing goal", {"task": "box_stacking", "start": {"state": START}}, 422, "goal"),
    (
        "invalid state",
        {**GOOD, "start": {"state": {"stacks": [["red", "red"], [], []]}}},
        422,
        "start",
    ),
    ("state of the wrong shape", {**GOOD, "goal": {"state": {"columns": 3}}}, 422, "goal"),
    ("image and state", {**GOOD, "start": {"state": START, "image": "AAAA"}}, 422, "start"),
    ("bad base64", {**GOOD, "start": {"image": "not base64!"}}, 422, "image"),
    (
        "not an image",
        {**GOOD, "start": {"image": base64.b64encode(b"GIF89a....").decode()}},
        422,
        "image",
    ),
    (
        "BMP, not PNG or JPEG",
        {**GOOD, "goal": {"image": image_of((64, 64), fmt="BMP")}},
        422,
        "image",
    ),
    ("too small", {**GOOD, "start": {"image": image_of((15, 64))}}, 422, "image"),
    ("transparent RGBA", {**GOOD, "start": {"image": image_of((64, 64), "RGBA")}}, 422, "image"),
    (  # a frame: decoded only in the encoder, its field still named
        "transparent RGBA frame",
        {**GOOD, "goal": {"image": image_of((400, 400), "RGBA")}},
        422,
        "goal",
    ),
    ("max_plans out of range", {**GOOD, "max_plans": 0}, 422, "max_plans"),
    ("max_plans not a number", {**GOOD, "max_plans": "many"}, 422, "max_plans"),
    ("robot_id not a key", {**GOOD, "robot_id": "a/b*"}, 422, "robot_id"),
    ("robot_id a verbatim chunk", {**GOOD, "robot_id": "@arm"}, 422, "robot_id"),
    ("unknown field", {**GOOD, "max_plan": 3}, 422, "max_plan"),
    ("body over the limit", {**GOOD, "start": {"image": "A" * (5 * 1024 * 1024)}}, 413, None),
]


@pytest.mark.parametrize(
    ("case", "body", "status", "field"), BAD_INPUTS, ids=[c[0] for c in BAD_INPUTS]
)
def test_bad_input_gets_a_4xx_naming_the_field(http, case, body, status, field):
    if isinstance(body, bytes):
        reply = http.post("/plan", content=body, headers={"content-type": "application/json"})
    else:
        reply = http.post("/plan", json=body)
    assert reply.status_code == status, reply.text
    if field is not None:
        assert field in json.dumps(reply.json()["detail"]), reply.text


def test_bad_input_on_the_other_routes(http):
    assert (
        http.post("/render", json={"task": "box_stacking", "state": START, "seed": -1}).status_code
        == 422
    )
    assert (
        http.post(
            "/execute",
            json={**GOOD, "max_steps": 10_000},
        ).status_code
        == 422
    )
    reply = http.post(
        "/execute",
        json={"task": "box_stacking", "start": {"image": "AAAA"}, "goal": {"state": GOAL}},
    )
    assert reply.status_code == 422 and "state" in reply.text  # execution starts from a state
    assert http.get("/health").status_code == 200  # and the service keeps serving


def test_execute_reaches_the_goal(http):
    reply = http.post("/execute", json={**GOOD, "seed": 3})
    assert reply.status_code == 200, reply.text
    body = reply.json()
    assert body["success"] and body["reason"] == "goal"
    assert body["final_state"] == TASK.state_to_json(TASK.parse_state(GOAL))
    assert body["final_view"] == body["final_state"]  # nothing of a box state hides
    assert 5 <= len(body["steps"]) <= 8  # the optimum is 5 moves
    assert all(
        Image.open(io.BytesIO(base64.b64decode(s["image"]))).size == (64, 64) for s in body["steps"]
    )


def robot_r2(stack, access, start: dict, goal: dict, *flags: str) -> subprocess.CompletedProcess:
    """`lsr robot` as robot r2 with its credentials, from `start` to `goal`; it must succeed."""
    ends = ["--start-state", json.dumps(start), "--goal-state", json.dumps(goal)]
    result = subprocess.run(
        [sys.executable, "-m", "services.cli", "robot", "--robot-id", "r2", *ends, *flags,
         "--connect", stack.config.endpoint],
        capture_output=True,
        text=True,
        timeout=120,
        env=as_role(access, "robot-r2"),
    )  # fmt: skip
    assert result.returncode == 0, result.stdout + result.stderr
    return result


def test_robot_client_reaches_its_goal_and_reports_what_it_did(stack, access):
    result = robot_r2(stack, access, START, GOAL, "--report")
    assert "[r2] step 1:" in result.stdout and "reached the goal" in result.stdout
    # Every executed step reached the gateway's experience folder over zenoh, with its action.
    steps = result.stdout.count("[r2] step ")
    recorded = load_dataset(Path(stack.config.env["LSR_EXPERIENCE_DIR"]) / "box_stacking")
    assert int(recorded.a.sum()) == steps >= 5
    assert f"[r2] {len(recorded)} experience tuples recorded" in result.stdout
    assert recorded.image1.shape[1:] == (64, 64, 3)  # its camera frames, registered
    state = TASK.parse_state(START)
    for u in recorded.u[recorded.a == 1]:
        state = TASK.apply(state, TASK.array_to_action(u))  # the actions as executed, in order
    assert state == TASK.parse_state(GOAL)


def test_robot_client_moves_the_rope_box_to_its_goal(stack, access):
    result = robot_r2(stack, access, ROPE_START, ROPE_GOAL, "--task", "rope_box")
    assert "[r2] step 2:" in result.stdout and "reached the goal" in result.stdout


def test_an_impostor_planner_and_strangers_are_refused_while_the_stack_serves(stack, http, access):
    # A robot's credentials (or another service's) do not let a process serve plans.
    impostors = []
    for role in ("robot-r2", "apn"):
        session = open_session(
            BusConfig(
                connect=[stack.config.endpoint],
                open_timeout_s=10,
                config_file=access / f"{role}.json5",
            )
        )
        server = Server(session, "planner", f"impostor-{role}")
        server.serve(service_key("planner", "box_stacking", "paths"), forged_paths)
        impostors.append((session, server))
    try:
        time.sleep(0.5)
        for _ in range(10):
            reply = http.post("/plan", json={**GOOD, "include_images": False})
            assert reply.status_code == 200, reply.text
            assert_plans_lead_from(START, GOAL, reply.json(), images=False)  # the real planner's
        planners = http.get("/health").json()["services"]["planner"]["instances"]
        assert [i["instance"] for i in planners if "impostor" in i["instance"]] == []
        with pytest.raises(ConnectionError):  # without credentials nobody joins at all
            open_session(BusConfig(connect=[stack.config.endpoint], open_timeout_s=1))
    finally:
        for session, server in impostors:
            server.close()
            close_quietly(session)


def forged_paths(_: bytes) -> PathsReply:
    """What an impostor would answer: a path that a robot must never execute."""
    return PathsReply(
        paths=[[0, 1]],
        supports=[[1]],
        node_ids=[0, 1],
        node_latents=WireArray.of(np.zeros((2, 64), np.float32)),
        model_id="forged",
    )


def plan_ok(http: httpx.Client) -> int:
    return http.post("/plan", json={**GOOD, "include_images": False}).status_code


def wait_for(predicate, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.3)


def planners(http: httpx.Client, task: str = "box_stacking") -> int:
    instances = http.get("/health").json()["services"]["planner"]["instances"]
    return sum(i["task"] == task for i in instances)


def test_a_replica_takes_over_when_one_is_killed(stack, http):
    stack.start_service("planner", name="planner-2")
    wait_for(lambda: planners(http) == 2)
    stack.stop("planner", sig=signal.SIGKILL)
    codes = [plan_ok(http) for _ in range(10)]
    assert codes == [200] * 10
    wait_for(lambda: planners(http) == 1)


def test_a_stopped_service_gives_503_by_name_then_recovers(stack, http):
    stack.stop("apn")
    started = time.monotonic()
    reply = http.post("/plan", json=GOOD)
    assert reply.status_code == 503 and "apn" in reply.json()["detail"]
    assert time.monotonic() - started < 5.0
    health = http.get("/health")
    assert health.status_code == 503 and health.json()["services"]["apn"]["status"] == "unavailable"
    stack.start_service("apn")
    wait_for(lambda: http.get("/health").status_code == 200)
    assert plan_ok(http) == 200


def test_lsr_up_refuses_ports_in_use(stack):
    config = StackConfig(port=stack.config.port, zenoh_port=free_port(), models=(MODEL,))
    with pytest.raises(ValueError, match="not free"):
        check_ports_free(config)


def children_of(pid: int) -> list[int]:
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            found.append(int(stat.parent.name))
    return found


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_lsr_up_starts_everything_and_a_signal_stops_it_all(sig, access):
    port, zenoh_port = free_port(), free_port()
    secure = ["--zenoh-access", str(access)] if sig == signal.SIGTERM else []  # both ways
    up = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "services.cli",
            "up",
            "--port",
            str(port),
            "--zenoh-port",
            str(zenoh_port),
            "--model",
            str(MODEL),
            *secure,
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        for line in up.stdout:
            if "LSR is up" in line:
                break
        assert f"http://127.0.0.1:{port}" in line
        children = children_of(up.pid)
        assert len(children) == 6  # router, four services, gateway
        assert httpx.get(f"http://127.0.0.1:{port}/health", timeout=10).status_code == 200
        if secure:  # the bus runs under access control: no credentials, no session
            with pytest.raises(ConnectionError):
                endpoint = f"tcp/127.0.0.1:{zenoh_port}"
                open_session(BusConfig(connect=[endpoint], open_timeout_s=1))
        up.send_signal(sig)
        assert up.wait(30) == 0
        for child in children:
            assert not Path(f"/proc/{child}").exists(), f"child {child} outlived lsr up"
    finally:
        if up.poll() is None:
            up.kill()
