"""The planner service's paths handler keeps a closed loop's place (`expect_node`) and the
steps it asks to avoid (`avoid_steps`)."""

import json
import shutil

import numpy as np
import pytest

from services.planner import service as planner_service
from services.planner.knowing import FILE as MATCH_FILE
from services.planner.roadmap import Roadmap
from services.runtime import ModelInfo, ServiceContext
from shared.checkpoint import MANIFEST, seal
from shared.messages import PathsRequest, WireArray, pack
from shared.settings import Settings


@pytest.fixture
def paths_handler(tiny_model, tmp_path):
    """The handler over a copy of the tiny model whose nodes each know every latent, so that
    a start image is known at any node it is told to expect."""
    model = tmp_path / "model"
    shutil.copytree(tiny_model[0], model)
    folder = model / "roadmap"
    match = json.loads((folder / MATCH_FILE).read_text())
    match["node_thresholds"] = [1e9] * len(match["node_thresholds"])
    (folder / MATCH_FILE).write_text(json.dumps(match))
    sealed = json.loads((folder / MANIFEST).read_text())["files"]
    seal(folder, list(sealed))
    info = ModelInfo.read(model)
    context = ServiceContext("planner", "x", info, None, Settings())
    yield planner_service.setup(context)["paths"], Roadmap.load(folder), info
    context.stopping.set()


def ask(handler, info, z_start, z_goal, expect_node=None, avoid_steps=()):
    request = PathsRequest(
        task=info.task,
        z_start=WireArray.of(z_start.astype(np.float32)),
        z_goal=WireArray.of(z_goal.astype(np.float32)),
        errors=WireArray.of(np.zeros((2, 3), np.float32)),
        expect_node=expect_node,
        avoid_steps=list(avoid_steps),
    )
    return handler(pack(request))


def test_paths_start_at_the_expected_node_where_the_start_is_known_there(paths_handler):
    """...unless Algorithm 1 would put the start in its own node and not in the expected one
    (the loop went elsewhere: services/planner/places.py)."""
    from services.planner.places import Places

    handler, roadmap, info = paths_handler
    places = Places.load(info.directory / "roadmap", roadmap)
    a, b = (int(n) for n in roadmap.edges[0])
    goal = roadmap.nodes[b]
    start = roadmap.nodes[a]
    assert ask(handler, info, start, goal).paths[0][0] == a
    assert places is not None and places.holds(start, a) and not places.holds(start, b)
    assert ask(handler, info, start, goal, expect_node=b).paths[0][0] == a
    away = roadmap.nodes[b] + 1.0  # known everywhere here, in no node by Algorithm 1
    assert not any(places.holds(away, n) for n in range(roadmap.num_nodes))
    assert ask(handler, info, away, goal, expect_node=b).paths == [[b]]
    # a node the roadmap does not have (another model's plan) is ignored
    assert ask(handler, info, start, goal, expect_node=roadmap.num_nodes + 5).paths[0][0] == a


def test_a_negative_expected_node_is_refused_by_name():
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="expect_node"):
        PathsRequest(
            task="box_stacking",
            z_start=WireArray.of(np.zeros(2, np.float32)),
            z_goal=WireArray.of(np.zeros(2, np.float32)),
            expect_node=-1,
        )


def test_the_steps_asked_to_avoid_reach_the_search(paths_handler, monkeypatch):
    handler, roadmap, info = paths_handler
    a, b = (int(n) for n in roadmap.edges[0])
    searched = []
    search = Roadmap.shortest_paths

    def spy(self, src, dst, max_paths=16, avoid=()):
        searched.append(list(avoid))
        return search(self, src, dst, max_paths, avoid)

    monkeypatch.setattr(Roadmap, "shortest_paths", spy)
    far = roadmap.num_nodes + 5  # a node of another roadmap version: that step is ignored
    reply = ask(handler, info, roadmap.nodes[a], roadmap.nodes[b], avoid_steps=[(a, b), (a, far)])
    assert searched[0] == [(a, b)]
    assert reply.paths == [[a, b]]  # the tiny roadmap is a tree: no way round, so through it
