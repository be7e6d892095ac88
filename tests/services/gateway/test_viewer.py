"""The plan viewer's routes without services: the page, its layout, its 4xx, its auth."""

from __future__ import annotations

import json

import httpx
import numpy as np
import pytest

from services.gateway.auth import digest
from services.gateway.viewer import Viewer, graph_layout, node_views
from services.planner.service import node_labels
from shared.messages import GraphReply, WireArray

KEY = "viewer-key-0123456789"
GOOD = {
    "task": "box_stacking",
    "start": {"state": {"stacks": [["red"], ["green"], ["blue", "yellow"]]}},
    "goal": {"state": {"stacks": [["blue"], ["red", "green"], ["yellow"]]}},
}


def test_the_layout_puts_neighbours_close_and_is_deterministic():
    ring = np.array([[i, (i + 1) % 12] for i in range(12)])
    ring.sort(axis=1)
    xy = graph_layout(12, ring)
    assert xy.shape == (12, 2) and xy.min() >= 0.05 - 1e-9 and xy.max() <= 0.95 + 1e-9
    near = np.linalg.norm(xy[ring[:, 0]] - xy[ring[:, 1]], axis=1).mean()
    opposite = np.linalg.norm(xy[:6] - xy[6:], axis=1).mean()
    assert near < opposite / 2
    np.testing.assert_array_equal(xy, graph_layout(12, ring))
    # Another component and lone nodes still get a place inside the frame.
    two = graph_layout(5, np.array([[0, 1], [1, 2]]))
    assert np.isfinite(two).all() and graph_layout(1, np.zeros((0, 2), int)).tolist() == [
        [0.5, 0.5]
    ]


def test_the_graph_names_each_nodes_twin_group_so_plans_step_between_groups(monkeypatch):
    # 0 - 1   2 - 3 - 4, and 1 ~ 2 ~ 4 twins through a chain: a plan 0 -> 2 -> 3 uses edge 0-1
    reply = GraphReply(
        node_latents=WireArray.of(np.zeros((5, 2), np.float32)),
        edges=WireArray.of(np.array([[0, 1], [2, 3]], np.int64)),
        edge_weights=WireArray.of(np.array([2, 5], np.int64)),
        twins=WireArray.of(np.array([[1, 2], [2, 4]], np.int64)),
        model_id="m",
    )
    viewer = Viewer(gateway=None)
    monkeypatch.setattr(viewer, "_call", lambda *args: reply)
    graph, _ = viewer.graph("box_stacking")
    assert [n.group for n in graph.nodes] == [0, 1, 1, 3, 1]
    assert graph.twins == [(1, 2), (2, 4)] and graph.edges == [(0, 1, 2), (2, 3, 5)]
    xy = np.array([[n.x, n.y] for n in graph.nodes])
    assert np.linalg.norm(xy[1] - xy[2]) < np.linalg.norm(xy[0] - xy[3])  # twins drawn close
    plain = reply.model_copy(update={"twins": None, "model_id": "older planner"})
    monkeypatch.setattr(viewer, "_call", lambda *args: plain)
    graph, _ = viewer.graph("box_stacking")
    assert [n.group for n in graph.nodes] == [0, 1, 2, 3, 4] and graph.twins == []


def test_nodes_show_their_views_with_the_hidden_sleeves_named():
    hidden = {"folds": ["left_sleeve", "left_side", "bottom_half"]}
    views = node_views("tshirt_folding", [hidden, {"folds": []}, None])
    assert views == [
        {"folds": ["left_side", "bottom_half"], "hidden": ["left_sleeve"]},
        {"folds": [], "hidden": []},
        None,
    ]
    box = {"stacks": [["red"], ["green"], ["blue", "yellow"]]}
    assert node_views("box_stacking", [box]) == [box]  # nothing of a box state hides


def test_node_labels_are_read_only_when_they_fit_the_roadmap(tmp_path):
    assert node_labels(tmp_path, 2) is None  # a model without labels
    labels = [{"node": i, "state": {"folds": []}, "purity": 0.5, "members": 3} for i in (1, 0)]
    (tmp_path / "labels.json").write_text(json.dumps(labels))
    assert node_labels(tmp_path, 2) == ([{"folds": []}] * 2, [0.5, 0.5])
    assert node_labels(tmp_path, 3) is None  # labels of another roadmap are not guessed onto it
    (tmp_path / "labels.json").write_text("{not json")
    assert node_labels(tmp_path, 2) is None


def test_the_page_is_served(http):
    page = http.get("/")
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    assert '<script src="/ui/app.js"' in page.text and "http" not in page.text.split("<body>")[0]
    for asset, kind in (("/ui/app.js", "javascript"), ("/ui/style.css", "text/css")):
        reply = http.get(asset)
        assert reply.status_code == 200 and kind in reply.headers["content-type"]
    assert http.get("/ui/nothing.js").status_code == 404


@pytest.mark.parametrize(
    ("method", "path", "body", "status", "named"),
    [
        ("GET", "/tasks/juggling/roadmap", None, 404, "juggling"),
        ("GET", "/tasks/box_stacking/roadmap/nodes/-1.png", None, 422, "node"),
        ("GET", "/tasks/box_stacking/roadmap/nodes/x.png", None, 422, "node"),
        ("POST", "/action-pixels", {"task": "box_stacking", "actions": []}, 422, "actions"),
        (
            "POST",
            "/action-pixels",
            {"task": "box_stacking", "actions": [{"pick": {"row": 9, "col": 0}}]},
            422,
            "actions.0",
        ),
        ("POST", "/execute/stream", {**GOOD, "start": {"state": {"stacks": []}}}, 422, "start"),
        ("POST", "/execute/stream", {**GOOD, "goal": {"state": {"folds": []}}}, 422, "goal"),
        ("POST", "/execute/stream", {**GOOD, "max_steps": 0}, 422, "max_steps"),
    ],
)
def test_bad_input_gets_a_4xx_naming_the_field(http, method, path, body, status, named):
    reply = http.request(method, path, json=body)
    assert reply.status_code == status, reply.text
    assert reply.headers["content-type"] == "application/json"  # not a stream
    assert named in json.dumps(reply.json()["detail"])


def test_a_missing_service_is_named_in_a_503_in_time(http):
    reply = http.get("/tasks/box_stacking/roadmap")  # no planner on this bus
    assert reply.status_code == 503 and "planner" in reply.json()["detail"]
    # The stream's input is checked before the episode starts; then the sim is missing.
    with http.stream("POST", "/execute/stream", json=GOOD) as stream:
        assert stream.status_code == 200
        assert stream.headers["content-type"].startswith("text/event-stream")
        events = stream.read().decode()
    assert events.startswith("event: started") and "event: error" in events
    error = json.loads(events.split("event: error\ndata: ")[1])
    assert error["status"] == 503 and "sim" in error["detail"]


@pytest.fixture(scope="module")
def locked(gateway_with):
    yield from gateway_with(api_key_hashes=digest(KEY))


def test_the_page_is_open_and_its_data_needs_the_key(locked):
    assert httpx.get(locked + "/").status_code == 200
    assert httpx.get(locked + "/ui/app.js").status_code == 200
    for path in ("/tasks/box_stacking/roadmap", "/tasks/box_stacking/roadmap/nodes/0.png"):
        assert httpx.get(locked + path).status_code == 401
    for path in ("/action-pixels", "/execute/stream"):
        assert httpx.post(locked + path, json={}).status_code == 401
    assert httpx.get(locked + "/uix").status_code == 401  # only the page's own prefix is open
