"""Experience end to end on the tiny model: recorded by the closed loop and by exploration in
the real simulator, grown into roadmap versions that every --model command then uses."""

import json
import shutil

import numpy as np
import pytest

from services.data.experience import ExperienceLog, Recorder
from services.planner import versions
from services.planner.action_plans import ActionPlanner
from services.planner.build import build_from_dataset
from services.planner.grow import grow_model
from services.planner.roadmap import Roadmap, RoadmapConfig
from services.sim.box_stacking.world import BoxStackingWorld
from services.sim.closed_loop import optimal_moves, run_episode
from services.sim.explore import ExploreConfig, explore
from shared.dataset import load_dataset
from shared.plans import VisualActionPlan
from shared.tasks.base import IllegalActionError


@pytest.fixture
def model(tiny_model, tmp_path):
    folder = tmp_path / "model"
    shutil.copytree(tiny_model[0], folder)
    return folder


@pytest.fixture(scope="module")
def small_world():
    with BoxStackingWorld(image_size=32) as w:
        yield w


class Oracle:
    """Plans one true shortest move at a time (the tiny model plans too badly to act)."""

    def __init__(self, world):
        self.world = world

    def plan(self, start, goal, max_plans=8, expect=None, avoid=()):
        task, state = self.world.task, self.world.read_state()
        move, _ = min(task.neighbours(state), key=lambda m: optimal_moves(task, m[1], self.goal))
        return [VisualActionPlan([0, 1], [start, goal], [move], [1.0], [1])]


def test_the_closed_loop_records_what_it_did_and_the_roadmap_grows_from_it(
    model, small_world, tmp_path, tiny_model
):
    task = small_world.task
    oracle = Oracle(small_world)
    experience = tmp_path / "exp"
    record = Recorder(ExperienceLog(experience, task.spec, 32), task)
    rng = np.random.default_rng(0)
    executed = 0
    for _ in range(3):
        start, oracle.goal = task.sample_state(rng), task.sample_state(rng)
        episode = run_episode(oracle, small_world, start, oracle.goal, rng, record=record)
        executed += len(episode.actions)
    record.flush()
    data = load_dataset(experience)
    assert int(data.a.sum()) == executed > 0
    moved = data.a == 1
    for u, s1, s2 in zip(data.u[moved], data.state1[moved], data.state2[moved], strict=True):
        start, after = task.array_to_state(s1), task.array_to_state(s2)
        assert task.apply(start, task.array_to_action(u)) == after  # what the world did

    before = Roadmap.load(versions.roadmap_dir(model))
    report = grow_model(model, [experience])
    assert report["version"] == "v2" and versions.current_version(model) == "v2"
    grown = Roadmap.load(versions.roadmap_dir(model))
    assert len(grown.point_node) == len(before.point_node) + 2 * len(data)
    assert grown.num_nodes == before.num_nodes + report["new_nodes"]
    assert np.array_equal(grown.nodes[: before.num_nodes], before.nodes)  # built nodes stay
    labels = json.loads((versions.roadmap_dir(model) / "labels.json").read_text())
    assert len(labels) == grown.num_nodes
    assert ActionPlanner.from_model_dir(model).planner.roadmap.num_nodes == grown.num_nodes

    with pytest.raises(ValueError, match="nothing new"):
        grow_model(model, [experience])  # the same tuples never count twice
    copy = tmp_path / "copy"  # nor from a copy (exported and imported, moved, ...)
    shutil.copytree(experience, copy)
    with pytest.raises(ValueError, match=f"{len(data)} tuples it holds already or twice"):
        grow_model(model, [copy])
    ExperienceLog(copy, task.spec, 32).append(
        data.image2[:1], data.image2[:1], data.u[:1] * 0 - 1, data.state2[:1], data.state2[:1]
    )  # one new tuple (a look again) in the copy: only it is taken
    assert grow_model(model, [copy])["tuples"] == 1
    with pytest.raises(ValueError, match="grown roadmap versions"):
        build_from_dataset(
            model / "vae", tiny_model[1], RoadmapConfig(min_samples=1), model / "roadmap"
        )  # a rebuild would go on planning with v2
    versions.make_current(model, "v1")  # a roll-back
    assert ActionPlanner.from_model_dir(model).planner.roadmap.num_nodes == before.num_nodes
    assert versions.versions(model) == ["v1", "v2", "v3"]


def test_exploration_spends_its_budget_in_the_simulator_and_grows_a_version(model, tmp_path):
    # The tiny model's proposals are mostly refused: whether 30 tries record any depends on the
    # seed and the APN's training (seed 1 recorded none once the APN learned moves both ways).
    cfg = ExploreConfig(actions=30, seed=0, grow_every=10, chain=2, seen_share=0.8)
    report = explore(model, cfg, tmp_path / "exp", progress=False)
    data = load_dataset(tmp_path / "exp")
    assert report["actions"] == 30 and len(data) == report["recorded"] > 0
    assert report["refused"] >= int((data.a == 0).sum())  # identical looks are not recorded
    assert report["growth"]["version"] == versions.current_version(model) == "v2"
    task = ActionPlanner.from_model_dir(model).task
    for u, s1, s2, a in zip(data.u, data.state1, data.state2, data.a, strict=True):
        start, after = task.array_to_state(s1), task.array_to_state(s2)
        if a:
            assert task.apply(start, task.array_to_action(u)) == after
        else:
            assert start == after


def test_exploration_looks_again_after_each_executed_action(model, tmp_path):
    # (as above: at seed 2 all of 24 tries were refused since the explorer also starts from
    # recorded images without a node; seed 1 records 3 moves)
    cfg = ExploreConfig(actions=24, seed=1, grow_every=6, chain=2, seen_share=0.8, looks=2)
    explore(model, cfg, tmp_path / "exp", progress=False)
    data = load_dataset(tmp_path / "exp")
    moved = np.flatnonzero(data.a == 1)
    assert len(moved) > 0
    for i in moved:  # each executed action is followed by two looks at the state it reached
        if i + 2 < len(data):
            assert not data.a[i + 1] and not data.a[i + 2]
            assert (data.state1[i + 1] == data.state2[i]).all()
            assert (data.state2[i + 2] == data.state2[i]).all()
            assert not np.array_equal(data.image1[i + 1], data.image2[i + 1])


def test_an_illegal_action_is_not_applied(small_world):
    task = small_world.task
    state = task.sample_state(np.random.default_rng(0))
    small_world.reset(state, np.random.default_rng(0))
    bad = task.array_to_action(np.array([0, 0, 0, 0], np.int8))
    with pytest.raises(IllegalActionError):
        small_world.execute(bad, np.random.default_rng(0))
    assert small_world.read_state() == state


def test_exploration_heads_for_neither_its_twin_nor_a_neighbour():
    from services.sim.explore import _target, shape_of

    # 1 - 0 ~ 1 twins - 2 - 3 - 4 on a line, one component: only 3 and 4 are worth a try
    nodes = np.array([[0, 0], [1, 0], [2, 0], [3, 0], [4, 0]], np.float32)
    edges = np.array([[0, 2], [2, 3], [3, 4]], np.int64)
    roadmap = Roadmap(
        config=RoadmapConfig(metric="l1"), epsilon=1.0, mu0=0.5, sigma0=0.5, nodes=nodes,
        node_sizes=np.full(5, 3, np.int64), edges=edges, edge_weights=np.ones(3, np.int64),
        point_node=np.repeat(np.arange(5, dtype=np.int64), 3), twins=np.array([[0, 1]]),
    )  # fmt: skip
    rng = np.random.default_rng(0)
    picked = {_target(roadmap, shape_of(roadmap), nodes[0], 0, 1.0, rng) for _ in range(40)}
    assert picked == {3, 4}


def test_exploration_heads_for_thin_nodes_more_often():
    from services.sim.explore import _target, shape_of

    # 0 alone; the rest in other components: 1 with no edge, 2 with one, 3 with three
    nodes = np.array([[0, 0], [1, 0], [0, 1], [-1, 0], [5, 5], [6, 6]], np.float32)
    edges = np.array([[2, 3], [3, 4], [3, 5]], np.int64)
    roadmap = Roadmap(
        config=RoadmapConfig(metric="l1"), epsilon=0.1, mu0=0.5, sigma0=0.5, nodes=nodes,
        node_sizes=np.full(6, 3, np.int64), edges=edges, edge_weights=np.ones(3, np.int64),
        point_node=np.repeat(np.arange(6, dtype=np.int64), 3), twins=np.zeros((0, 2), np.int64),
    )  # fmt: skip
    rng = np.random.default_rng(0)
    picked = [_target(roadmap, shape_of(roadmap), nodes[0], 0, 1.0, rng) for _ in range(600)]
    counts = np.bincount(picked, minlength=6)
    assert counts[1] > counts[2] > counts[3] > 0  # weights 1, 1/4, 1/16 (4 and 5: 1/4 each)


def test_members_are_encoded_only_from_the_data_the_roadmap_was_built_on(
    model, tiny_model, tmp_path
):
    from services.encoder.checkpoint import load_vae
    from services.planner.grow import load_members
    from services.planner.members import MEMBERS
    from services.sim.datagen import GenerateConfig, generate

    (versions.roadmap_dir(model) / MEMBERS).unlink()  # a roadmap built before they were kept
    vae, _ = load_vae(model / "vae")
    assert len(load_members(model, vae, tiny_model[1]).points) == 120
    other = tmp_path / "other"  # as many tuples, other images: the data generated again
    generate(GenerateConfig(pairs=60, seed=2, image_size=32, workers=1), other, progress=False)
    with pytest.raises(ValueError, match="not the data it was built on"):
        load_members(model, vae, other)


def _starts_by_state(
    order: list, point_node: list[int], edges: list[list[int]], a: list[int], has_state: list[int]
) -> dict[str, float]:
    """`starts` on a roadmap of 2-D nodes and members showing box states `order` (two images a
    tuple), keyed by each start's repr; no state may start twice."""
    from services.planner.members import Members
    from services.sim.explore import shape_of, starts
    from shared.tasks import get_task

    task = get_task("box_stacking")
    k, n = max(point_node) + 1, len(a)
    roadmap = Roadmap(
        config=RoadmapConfig(metric="l1"), epsilon=0.1, mu0=0.5, sigma0=0.5,
        nodes=np.arange(2 * k, dtype=np.float32).reshape(k, 2) * 5,
        node_sizes=np.ones(k, np.int64), edges=np.array(edges, np.int64).reshape(-1, 2),
        edge_weights=np.ones(len(edges), np.int64), point_node=np.array(point_node, np.int64),
        twins=np.zeros((0, 2), np.int64),
    )  # fmt: skip
    members = Members(
        points=np.zeros((2 * n, 2), np.float32), errors=np.zeros((2 * n, 3), np.float32),
        actions=np.full((n, 4), -1, np.int8), a=np.array(a, np.uint8),
        states=np.stack([task.state_to_array(s) for s in order]),
        has_state=np.array(has_state, np.uint8), experience=np.zeros(n, np.uint8),
        keys=np.zeros(n, np.uint64),
    )  # fmt: skip
    places, weight = starts(task, roadmap, shape_of(roadmap), members)
    by_place = dict(zip(map(repr, places), weight.tolist(), strict=True))
    assert len(by_place) == len(places)  # each recorded state once
    return by_place


def test_exploration_starts_also_where_a_recorded_image_has_no_node():
    from shared.tasks import get_task

    # nodes 0 - 1 joined; tuple 0 a move 0 -> 1, tuple 1 a state seen standing still (no
    # node), tuple 2 a robot's no-action pair without states (no node: not a start)
    rng = np.random.default_rng(0)
    drawn = [get_task("box_stacking").sample_state(rng) for _ in range(3)]
    by_place = _starts_by_state(
        [*drawn, drawn[2], drawn[0], drawn[0]], [0, 1, -1, -1, -1, -1], [[0, 1]], [1, 0, 0],
        [1, 1, 1, 1, 0, 0],
    )  # fmt: skip
    # one edge in a group of two; the state seen standing still once, as a node alone
    assert by_place == {repr(drawn[0]): 0.25, repr(drawn[1]): 0.25, repr(drawn[2]): 1.0}


def test_exploration_weighs_a_state_by_its_best_joined_node():
    from shared.tasks import get_task

    # nodes 0 - 1 - 2 joined, node 3 alone; node 3 and a loose image show node 0's state (a
    # twin split off by its looks): that state is joined, it asks as little as node 0
    rng = np.random.default_rng(1)
    drawn = [get_task("box_stacking").sample_state(rng) for _ in range(3)]
    by_place = _starts_by_state(
        [drawn[0], drawn[1], drawn[1], drawn[2], drawn[0], drawn[0]], [0, 1, 1, 2, 3, -1],
        [[0, 1], [1, 2]], [1, 1, 0], [1] * 6,
    )  # fmt: skip
    assert len(by_place) == 3
    assert by_place[repr(drawn[0])] == by_place[repr(drawn[2])] == 1 / 6  # one edge, 3 nodes
    assert by_place[repr(drawn[1])] == 1 / 9
