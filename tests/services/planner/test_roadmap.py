import itertools
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from safetensors.numpy import load_file, save_file

from services.planner import roadmap as rm
from services.planner.roadmap import (
    ARRAYS_NAME,
    Roadmap,
    RoadmapConfig,
    RoadmapError,
    build_roadmap,
    pair_distances,
)

METRICS = ["l1", "l2", "inf"]
REFERENCE = (
    Path(__file__).resolve().parents[3].parent
    / "shared/reference/data/lsr_v1_box_stacking_latents.npz"
)


# ------------------------------------------------------------------------------------------
# Building on synthetic latents with a known answer
# ------------------------------------------------------------------------------------------

N_CLASSES = 20
# Known class graph: a ring plus chords; edge k is supported by (k % 3) + 1 action pairs.
GRAPH = sorted({(i, (i + 1) % N_CLASSES) for i in range(N_CLASSES)} | {(0, 10), (3, 15), (7, 12)})
GRAPH = [(min(i, j), max(i, j)) for i, j in GRAPH]
SMALL, ISOLATED, DANGLING = 20, 21, 22  # extra classes the pruning must remove


def synthetic(seed=0):
    """Well-separated classes in 8-D; returns z1, z2, a and each point's class."""
    rng = np.random.default_rng(seed)
    centres = rng.normal(0.0, 10.0, size=(23, 8))
    pairs = []
    for c in range(N_CLASSES):
        pairs += [(c, c, 0)] * 6
    for k, (i, j) in enumerate(GRAPH):
        for r in range(k % 3 + 1):
            pairs.append((i, j, 1) if r % 2 == 0 else (j, i, 1))
    pairs += [(SMALL, 5, 1)]  # 2 members: too small; its edges go with it
    pairs += [(ISOLATED, ISOLATED, 0)] * 3  # big enough, but no action pair at all
    pairs += [(DANGLING, DANGLING, 0)] * 2 + [(DANGLING, SMALL, 1)]  # isolated after pruning
    order = rng.permutation(len(pairs))
    c1, c2, a = np.array(pairs)[order].T
    noise = np.where(np.arange(23) < N_CLASSES, 0.01, 0.0)  # the extra classes stay in one piece
    z1 = centres[c1] + rng.normal(size=(len(a), 8)) * noise[c1, None]
    z2 = centres[c2] + rng.normal(size=(len(a), 8)) * noise[c2, None]
    classes = np.empty(2 * len(a), dtype=np.int64)
    classes[0::2], classes[1::2] = c1, c2
    return z1.astype(np.float32), z2.astype(np.float32), a.astype(np.int8), classes


def node_of_class(roadmap, classes):
    mapping = {}
    for c in range(N_CLASSES):
        nodes = set(roadmap.point_node[classes == c].tolist())
        assert len(nodes) == 1 and -1 not in nodes, (c, nodes)
        mapping[c] = nodes.pop()
    assert sorted(mapping.values()) == list(range(N_CLASSES))
    return mapping


def test_default_pruning_keeps_a_small_region_whose_moves_no_big_region_shows():
    """A small region with a big region's move (the same action into the same region) is a
    fragment of that region's state; one whose moves no big region shows is a state seen
    rarely, kept by the default pruning and pruned by an explicit min_samples."""
    rng = np.random.default_rng(0)
    big_a, big_b, big_c, fragment, rare = range(5)
    centres = rng.normal(0.0, 10.0, size=(5, 8))
    pairs = [(c, c, 0, -1) for c in (big_a, big_b, big_c) for _ in range(20)]
    pairs += [(big_a, big_b, 1, 0), (big_b, big_c, 1, 1)] * 3
    pairs += [(fragment, big_b, 1, 0), (rare, big_c, 1, 2)]
    c1, c2, a, action = (np.array(column) for column in zip(*pairs, strict=True))
    z1 = (centres[c1] + rng.normal(size=(len(a), 8)) * 0.01).astype(np.float32)
    z2 = (centres[c2] + rng.normal(size=(len(a), 8)) * 0.01).astype(np.float32)
    point_class = np.stack([c1, c2], axis=1).ravel()

    roadmap = build_roadmap(z1, z2, a.astype(np.int8), RoadmapConfig(), action)
    assert roadmap.stats["min_samples"] > 1
    assert (roadmap.point_node[point_class == fragment] == -1).all()
    assert (roadmap.point_node[point_class == rare] >= 0).all()
    assert roadmap.num_nodes == 4 and roadmap.stats["small_regions_kept"] == 1
    least = roadmap.stats["min_samples"]
    for pruned in (
        build_roadmap(z1, z2, a.astype(np.int8), RoadmapConfig(min_samples=least), action),
        build_roadmap(z1, z2, a.astype(np.int8), RoadmapConfig()),  # moves unknown
        build_roadmap(z1, z2, a.astype(np.int8), RoadmapConfig(keep_rare=False), action),
    ):
        assert pruned.num_nodes == 3 and (pruned.point_node[point_class == rare] == -1).all()


@pytest.mark.parametrize("metric", METRICS)
@pytest.mark.parametrize("eps_rule", ["paper", "stable"])
def test_build_recovers_classes_and_graph(metric, eps_rule):
    z1, z2, a, classes = synthetic()
    config = RoadmapConfig(metric=metric, eps_rule=eps_rule, min_samples=3)
    roadmap = build_roadmap(z1, z2, a, config)
    mapping = node_of_class(roadmap, classes)
    assert roadmap.nodes.shape == (N_CLASSES, 8) and roadmap.nodes.dtype == np.float32
    for c in (SMALL, ISOLATED, DANGLING):
        assert (roadmap.point_node[classes == c] == -1).all()

    expected = {}
    for k, (i, j) in enumerate(GRAPH):
        u, v = sorted((mapping[i], mapping[j]))
        expected[(u, v)] = k % 3 + 1
    got = dict(zip(map(tuple, roadmap.edges.tolist()), roadmap.edge_weights.tolist(), strict=True))
    assert got == expected  # each supporting action pair counted once
    assert roadmap.edges.dtype == np.int64 and roadmap.edges.shape == (len(GRAPH), 2)
    assert (roadmap.edges[:, 0] < roadmap.edges[:, 1]).all()
    assert roadmap.edges.tolist() == sorted(roadmap.edges.tolist())

    stats = roadmap.stats
    assert stats["regions_before_pruning"] == 23
    assert stats["edges_before_pruning"] == len(GRAPH) + 2
    assert stats["edge_weight_before_pruning"] == int(a.sum())
    assert stats["regions_too_small"] == 1 and stats["regions_isolated"] == 2
    assert (stats["nodes"], stats["edges"]) == (N_CLASSES, len(GRAPH))
    assert set(stats["seconds"]) >= {"phase1", "epsilon", "phase2", "phase3", "total"}
    json.dumps(stats)  # plain JSON types only

    points = np.empty((2 * len(a), 8), dtype=np.float32)
    points[0::2], points[1::2] = z1, z2
    for node in range(roadmap.num_nodes):
        members = points[roadmap.point_node == node]
        assert roadmap.node_sizes[node] == len(members)
        dist = pair_distances(members, np.broadcast_to(members.mean(0), members.shape), metric)
        assert np.array_equal(roadmap.nodes[node], members[np.argmin(dist)])  # a member
    # Nodes are numbered by the smallest point index of their region.
    firsts = [int(np.flatnonzero(roadmap.point_node == k)[0]) for k in range(N_CLASSES)]
    assert firsts == sorted(firsts)


def test_build_epsilon_and_pruning_thresholds():
    z1, z2, a, classes = synthetic()
    config = RoadmapConfig(metric="l2", w_eps=0.5, min_samples=1, eps_rule="paper")
    roadmap = build_roadmap(z1, z2, a, config)
    d0 = np.linalg.norm(z1[a == 0].astype(np.float64) - z2[a == 0], axis=1)
    assert roadmap.mu0 == pytest.approx(d0.mean(), rel=1e-12)
    assert roadmap.sigma0 == pytest.approx(d0.std(ddof=0), rel=1e-12)
    assert roadmap.epsilon == pytest.approx(d0.mean() + 0.5 * d0.std(), rel=1e-12)
    # min_samples 1 keeps the small class and its neighbour; the isolated class still goes.
    assert roadmap.num_nodes == N_CLASSES + 2
    assert (roadmap.point_node[classes == ISOLATED] == -1).all()
    assert (roadmap.point_node[classes == SMALL] >= 0).all()
    assert roadmap.stats["regions_isolated"] == 1


def test_edges_fewer_pairs_support_than_min_edge_weight_are_dropped(tmp_path):
    z1, z2, a, _ = synthetic(seed=5)
    config = RoadmapConfig(metric="l2", w_eps=0.5, min_samples=1, eps_rule="paper")
    every = build_roadmap(z1, z2, a, config)
    floor = int(np.sort(every.edge_weights)[len(every.edges) // 2])  # drops about half
    strong = build_roadmap(z1, z2, a, replace(config, min_edge_weight=floor))
    assert (strong.edge_weights >= floor).all() and len(strong.edges) < len(every.edges)
    kept = {(a, b) for a, b in every.edges[every.edge_weights >= floor].tolist()}
    assert len(kept) == len(strong.edges) == len(every.edges) - strong.stats["edges_too_weak"]
    strong.save(tmp_path / "strong")
    assert Roadmap.load(tmp_path / "strong").config.min_edge_weight == floor
    every.save(tmp_path / "every")  # the paper's: no key, readable by code from before it
    assert "min_edge_weight" not in (tmp_path / "every" / rm.JSON_NAME).read_text()
    with pytest.raises(RoadmapError, match="min_edge_weight must be an integer >= 1"):
        RoadmapConfig(min_edge_weight=0)


def test_build_is_deterministic():
    z1, z2, a, _ = synthetic(seed=4)
    r1 = build_roadmap(z1, z2, a)
    r2 = build_roadmap(z1, z2, a)
    for key in rm._ARRAY_KEYS:
        assert np.array_equal(getattr(r1, key), getattr(r2, key))


def test_build_strict_epsilon_on_pairs():
    # Every no-action pair is exactly 1 apart in every metric: epsilon = 1, and '<' keeps the
    # two latents of each pair in different regions.
    z1 = np.arange(12, dtype=np.float32).reshape(4, 3) * 8
    z2 = z1.copy()
    z2[:, 0] += 1
    config = RoadmapConfig(min_samples=1, eps_rule="paper")
    roadmap = build_roadmap(z1, z2, np.zeros(4, dtype=np.int8), config)
    assert roadmap.epsilon == 1.0
    assert roadmap.stats["regions_before_pruning"] == 8
    assert roadmap.num_nodes == 0  # no action pairs: every node is isolated


def test_build_defaults_follow_the_data():
    # Three images a state: a no-action pair 1 apart, and the image its actions start from
    # and end in, 2.5 away; states 40+ apart. The paper's epsilon (mu0 + sigma0, about 1)
    # splits every state in two; the stable rule joins them.
    rng = np.random.default_rng(3)
    centres = rng.normal(0.0, 30.0, size=(40, 8))
    e0, e1 = np.eye(8)[0], np.eye(8)[1]
    still = centres + 0.0
    z1 = np.r_[still, centres + 2.5 * e1]
    z2 = np.r_[
        still + e0 * rng.uniform(0.99, 1.01, size=(40, 1)), np.roll(centres, 1, 0) + 2.5 * e1
    ]
    a = np.r_[np.zeros(40), np.ones(40)].astype(np.int8)
    paper = build_roadmap(z1, z2, a, RoadmapConfig(eps_rule="paper", min_samples=1))
    default = build_roadmap(z1, z2, a)
    assert paper.stats["regions_before_pruning"] > 40
    assert default.stats["eps_rule"] == "stable" and default.epsilon > paper.epsilon
    assert default.stats["regions_before_pruning"] == default.num_nodes == 40
    assert len(default.edges) == 40 and default.stats["min_samples"] == 1  # 3 a region
    assert default.config == RoadmapConfig()
    # Without a stable range (latents without structure) Algorithm 1's epsilon is used.
    noise = rng.uniform(size=(2, 100, 3)) / 20
    flags = np.arange(100) % 2
    fallback = build_roadmap(noise[0], noise[1], flags, RoadmapConfig(min_samples=1))
    as_written = build_roadmap(noise[0], noise[1], flags, RoadmapConfig(eps_rule="paper"))
    assert fallback.stats["eps_rule"] == "paper" and fallback.epsilon == as_written.epsilon


def test_min_samples_default_scales_with_the_data():
    z1, z2, a, _ = synthetic()
    dense = np.tile(np.arange(len(a)), 10)  # every tuple ten times
    roadmap = build_roadmap(z1[dense], z2[dense], a[dense], RoadmapConfig(eps_rule="paper"))
    assert roadmap.stats["min_samples"] > 1 and (roadmap.node_sizes >= 10).all()
    once = build_roadmap(z1, z2, a, RoadmapConfig(eps_rule="paper"))
    assert once.stats["min_samples"] == 1


def test_roadmaps_saved_before_eps_rule_load_as_algorithm_1(tmp_path):
    z1, z2, a, _ = synthetic()
    build_roadmap(z1, z2, a, RoadmapConfig(eps_rule="paper", min_samples=3)).save(tmp_path)
    meta = json.loads((tmp_path / "roadmap.json").read_text())
    del meta["config"]["eps_rule"]
    (tmp_path / "roadmap.json").write_text(json.dumps(meta))
    assert Roadmap.load(tmp_path).config == RoadmapConfig(
        eps_rule="paper", min_samples=3, matching="whitened"
    )


def test_roadmaps_saved_before_whitening_match_in_the_metric(tmp_path):
    z1, z2, a, _ = synthetic()
    build_roadmap(z1, z2, a, RoadmapConfig(matching="metric")).save(tmp_path)
    meta = json.loads((tmp_path / "roadmap.json").read_text())
    # as older code wrote them, and can read them
    assert "matching" not in meta["config"]
    assert "whitening" not in load_file(str(tmp_path / "roadmap.safetensors"))
    loaded = Roadmap.load(tmp_path)
    assert loaded.config.matching == "metric" and loaded.whitening.shape == (0, 0)


def test_build_rejects_bad_input():
    z1, z2, a, _ = synthetic()
    with pytest.raises(RoadmapError, match="no-action"):
        build_roadmap(z1[a == 1], z2[a == 1], a[a == 1])
    with pytest.raises(RoadmapError, match="shape"):
        build_roadmap(z1, z2[:-1], a)
    with pytest.raises(RoadmapError, match="a must"):
        build_roadmap(z1, z2, a * 2)
    bad = z1.copy()
    bad[0, 0] = np.nan
    with pytest.raises(RoadmapError, match="finite"):
        build_roadmap(bad, z2, a)
    bad_configs = (
        {"metric": "l3"},
        {"w_eps": float("nan")},
        {"min_samples": 0},
        {"min_samples": 2.5},
        {"eps_rule": "auto"},
    )
    for kwargs in bad_configs:
        with pytest.raises(RoadmapError):
            RoadmapConfig(**kwargs)
    assert issubclass(RoadmapError, ValueError)


# ------------------------------------------------------------------------------------------
# Queries
# ------------------------------------------------------------------------------------------


def make_roadmap(nodes, edges, metric="l1"):
    nodes = np.asarray(nodes, dtype=np.float32)
    edges = np.asarray(sorted(edges), dtype=np.int64).reshape(-1, 2)
    return Roadmap(
        config=RoadmapConfig(metric=metric),
        epsilon=1.0,
        mu0=0.5,
        sigma0=0.5,
        nodes=nodes,
        node_sizes=np.full(len(nodes), 3, dtype=np.int64),
        edges=edges,
        edge_weights=np.ones(len(edges), dtype=np.int64),
        point_node=np.repeat(np.arange(len(nodes), dtype=np.int64), 3),
    )


def grid_roadmap(rows, cols):
    """Node r * cols + c at (r, c), edges between 4-neighbours."""
    nodes = [(r, c) for r in range(rows) for c in range(cols)]
    edges = [(r * cols + c, r * cols + c + 1) for r in range(rows) for c in range(cols - 1)]
    edges += [(r * cols + c, (r + 1) * cols + c) for r in range(rows - 1) for c in range(cols)]
    return make_roadmap(nodes, edges)


def test_shortest_paths_grid():
    grid = grid_roadmap(2, 3)  # 0 1 2 / 3 4 5
    assert grid.shortest_paths(0, 5) == [[0, 1, 2, 5], [0, 1, 4, 5], [0, 3, 4, 5]]
    assert grid.shortest_paths(5, 0) == [[5, 2, 1, 0], [5, 4, 1, 0], [5, 4, 3, 0]]
    assert grid.shortest_paths(0, 5, max_paths=2) == [[0, 1, 2, 5], [0, 1, 4, 5]]
    assert grid.shortest_paths(0, 5, max_paths=1) == [[0, 1, 2, 5]]
    assert grid.shortest_paths(4, 4) == [[4]]
    assert grid.shortest_paths(0, 1) == [[0, 1]]
    assert grid.neighbours(4) == [1, 3, 5]


def test_shortest_paths_avoid_steps_in_their_direction_unless_every_path_takes_them():
    grid = grid_roadmap(2, 3)  # 0 1 2 / 3 4 5
    assert grid.shortest_paths(0, 5, avoid=[(1, 4)]) == [[0, 1, 2, 5], [0, 3, 4, 5]]
    assert grid.shortest_paths(0, 5, avoid=[(0, 1)]) == [[0, 3, 4, 5]]
    assert grid.shortest_paths(0, 5, avoid=[(4, 1)]) == grid.shortest_paths(0, 5)  # other way
    assert grid.shortest_paths(0, 2, avoid=[(1, 2)]) == [[0, 1, 4, 5, 2], [0, 3, 4, 5, 2]]
    # no way left: the steps without which there is none are let go, the newest kept first
    assert grid.shortest_paths(0, 5, avoid=[(0, 1), (0, 3)]) == [[0, 1, 2, 5], [0, 1, 4, 5]]
    bridge = make_roadmap(np.zeros((6, 2)), [(0, 1), (1, 2), (0, 3), (2, 3), (2, 5)])
    assert bridge.shortest_paths(0, 5, avoid=[(0, 1), (2, 5)]) == [[0, 3, 2, 5]]
    with pytest.raises(RoadmapError, match="avoid must be a node id"):
        grid.shortest_paths(0, 5, avoid=[(0, 9)])
    with pytest.raises(RoadmapError, match="avoid must be a node id"):
        grid.shortest_paths(0, 0, avoid=[(0, 9)])  # checked before the trivial answer
    for bad in ([(0, 1, 2)], [5]):
        with pytest.raises(RoadmapError, match="avoid must hold steps"):
            grid.shortest_paths(0, 5, avoid=bad)


def one_way(roadmap, shown):
    """The roadmap as built for a task without undo, its action pairs going the `shown` ways
    (each by a move of its own: no turn is forbidden)."""
    exits = [(a, b, k) for k, (a, b) in enumerate(sorted(shown))]
    exits = np.array(exits, np.int64).reshape(-1, 3)
    return replace(roadmap, config=replace(roadmap.config, one_way=True), exits=exits)


def test_one_way_paths_take_a_step_against_its_pairs_only_where_nothing_else_reaches():
    grid = grid_roadmap(2, 3)  # 0 1 2 / 3 4 5
    both = {(a, b) for a, b in grid.edges.tolist()} | {(b, a) for a, b in grid.edges.tolist()}
    # 1 -> 2 shown only as 2 -> 1: 0 to 2 goes round rather than against it
    road = one_way(grid, both - {(1, 2)})
    assert road.unshown == [(1, 2)]
    assert road.shortest_paths(0, 2) == [[0, 1, 4, 5, 2], [0, 3, 4, 5, 2]]
    assert road.shortest_paths(2, 0) == grid.shortest_paths(2, 0)  # the shown way is shortest
    assert replace(road, config=grid.config).shortest_paths(0, 2) == [[0, 1, 2]]  # two-way
    assert replace(road, exits=np.zeros((0, 3), np.int64)).unshown == []  # no record: no ways
    # every way onward is unshown: the fewest are let go, the loop's own avoided steps last
    chain = one_way(make_roadmap(np.zeros((3, 2)), [(0, 1), (1, 2)]), {(1, 0), (2, 1)})
    assert chain.shortest_paths(0, 2) == [[0, 1, 2]]
    assert chain.shortest_paths(0, 2, avoid=[(0, 1)]) == [[0, 1, 2]]
    road = one_way(grid, both - {(1, 2), (4, 5)})
    assert road.shortest_paths(0, 2, avoid=[(5, 2)]) == [[0, 1, 2]]
    assert one_way(grid, both).shortest_paths(0, 5) == grid.shortest_paths(0, 5)
    disconnected = one_way(make_roadmap(np.zeros((3, 2)), [(0, 1)]), {(1, 0)})
    assert disconnected.shortest_paths(0, 2) == []
    # with memory (node 4 leads to 3 and 5 by one move): the turn 3 -> 4 -> 5 is not taken
    road = one_way(grid, both - {(1, 2)})
    exits = [e for e in road.exits.tolist() if e[0] != 4] + [[4, 3, 99], [4, 5, 99], [4, 1, 98]]
    road = replace(road, exits=np.array(sorted(exits), np.int64))
    assert road.turns and road.shortest_paths(0, 2) == [[0, 1, 4, 5, 2]]
    assert road.shortest_paths(0, 2, avoid=[(1, 4)]) == [[0, 1, 2]]


def test_one_way_is_saved_only_where_true(tmp_path):
    grid = grid_roadmap(2, 3)
    road = one_way(grid, {(0, 1)})
    road.save(tmp_path / "one")
    assert json.loads((tmp_path / "one" / "roadmap.json").read_text())["config"]["one_way"]
    assert Roadmap.load(tmp_path / "one").unshown == road.unshown
    grid.save(tmp_path / "two")
    assert "one_way" not in json.loads((tmp_path / "two" / "roadmap.json").read_text())["config"]
    with pytest.raises(RoadmapError, match="one_way must be true or false"):
        RoadmapConfig(one_way=1)


def test_shortest_paths_are_all_shortest_paths_in_order():
    grid = grid_roadmap(3, 4)
    paths = grid.shortest_paths(0, 11, max_paths=100)
    assert len(paths) == 10  # C(5, 2) monotone lattice paths
    assert paths == sorted(paths) and len({tuple(p) for p in paths}) == 10
    edges = set(map(tuple, grid.edges.tolist()))
    for path in paths:
        assert len(path) == 6 and path[0] == 0 and path[-1] == 11
        assert all((min(u, v), max(u, v)) in edges for u, v in itertools.pairwise(path))
    assert grid.shortest_paths(0, 11, max_paths=4) == paths[:4]
    assert grid.shortest_paths(0, 11, max_paths=100) == paths  # deterministic


def test_supports_are_the_edge_weights_along_a_path_either_way():
    grid = grid_roadmap(2, 3)  # 0 1 2 / 3 4 5
    grid.edge_weights[:] = np.arange(1, len(grid.edges) + 1)
    weight = {tuple(e): int(w) for e, w in zip(grid.edges.tolist(), grid.edge_weights, strict=True)}
    path = [0, 1, 4, 5]
    expected = [weight[(0, 1)], weight[(1, 4)], weight[(4, 5)]]
    assert grid.supports(path) == expected
    assert grid.supports(path[::-1]) == expected[::-1]
    assert grid.supports([4]) == []
    with pytest.raises(RoadmapError, match="not an edge"):
        grid.supports([0, 4])
    with pytest.raises(RoadmapError, match="not an edge"):
        grid.supports([5, 6])  # past the last node id


def test_shortest_paths_unconnected_and_errors():
    roadmap = make_roadmap([(0, 0), (1, 0), (5, 5), (6, 5)], [(0, 1), (2, 3)])
    assert roadmap.shortest_paths(0, 3) == []
    assert roadmap.neighbours(2) == [3]
    for args in ((0, 4), (-1, 0), (0, 1.5)):
        with pytest.raises(RoadmapError):
            roadmap.shortest_paths(*args)
    with pytest.raises(RoadmapError, match="max_paths"):
        roadmap.shortest_paths(0, 1, max_paths=0)


@pytest.mark.parametrize(("metric", "expected"), [("l1", 0), ("l2", 2), ("inf", 1)])
def test_nearest_node_uses_the_metric(metric, expected):
    # From the origin: L1 1.0 / 1.6 / 1.25, L2 1.0 / 1.13 / 0.97, Linf 1.0 / 0.8 / 0.9.
    roadmap = make_roadmap([(1.0, 0.0), (0.8, 0.8), (0.9, 0.35)], [(0, 1), (1, 2)], metric)
    assert roadmap.nearest_node(np.zeros(2)) == expected
    assert isinstance(roadmap.nearest_node(np.zeros(2)), int)
    batch = roadmap.nearest_node(np.array([[0.0, 0.0], [0.8, 0.79], [1.0, 0.01]]))
    assert batch.dtype == np.int64 and batch.tolist() == [expected, 1, 0]
    with pytest.raises(RoadmapError, match="shape"):
        roadmap.nearest_node(np.zeros(3))
    if metric == "l1":
        assert roadmap.nearest_nodes(np.zeros(2), 3).tolist() == [0, 2, 1]
        assert roadmap.nearest_nodes(np.zeros((2, 2)), 2).tolist() == [[0, 2], [0, 2]]
    with pytest.raises(RoadmapError, match=r"k must lie in 1\.\.3"):
        roadmap.nearest_nodes(np.zeros(2), 4)


def spread_roadmap(matching="whitened", per_node=20):
    """Two states whose images spread widely along x and barely along y; their nodes lie 2
    apart in x and 0.6 in y, so that an image of the first can lie nearer the second in L1."""
    rng = np.random.default_rng(0)
    centres = np.array([[0.0, 0.0], [2.0, 0.6]])
    node = np.repeat([0, 1], per_node)
    points = (centres[node] + rng.normal(size=(len(node), 2)) * [1.0, 0.1]).astype(np.float32)
    whitening = rm.fit_whitening(points, node) if matching == "whitened" else None
    return replace(
        make_roadmap(centres, [(0, 1)]),
        config=RoadmapConfig(matching=matching),
        point_node=node.astype(np.int64),
        whitening=np.zeros((0, 0), np.float32) if whitening is None else whitening,
    )


def test_whitened_matching_follows_the_spread_of_images_within_nodes():
    image_of_first = np.array([1.4, 0.0])  # L1: 1.4 to its node, 1.2 to the other
    assert spread_roadmap("metric").nearest_node(image_of_first) == 1
    whitened = spread_roadmap("whitened")
    assert whitened.whitening.shape == (2, 2)
    assert whitened.nearest_node(image_of_first) == 0
    assert whitened.nearest_node(np.array([[2.5, 0.6], [-1.0, 0.05]])).tolist() == [1, 0]


def test_whitening_needs_enough_images_sharing_a_node():
    assert spread_roadmap("whitened", per_node=2).whitening.shape == (0, 0)  # 2 dof, 2 dims
    lone = rm.fit_whitening(np.zeros((6, 2), np.float32), np.arange(6))  # one image a node
    assert lone.shape == (0, 0)
    z1, z2, a, _ = synthetic()
    built = build_roadmap(z1, z2, a)
    assert built.config.matching == "whitened" and built.whitening.shape == (8, 8)
    assert build_roadmap(z1, z2, a, RoadmapConfig(matching="metric")).whitening.size == 0
    with pytest.raises(RoadmapError, match="matching"):
        RoadmapConfig(matching="nearest")
    with pytest.raises(RoadmapError, match="whitening must have shape"):
        replace(built, whitening=np.eye(3, dtype=np.float32))
    with pytest.raises(RoadmapError, match="whitening given, but the config matches by metric"):
        replace(built, config=RoadmapConfig(matching="metric"))


# ------------------------------------------------------------------------------------------
# Save and load
# ------------------------------------------------------------------------------------------


def test_save_load_round_trip(tmp_path):
    z1, z2, a, _ = synthetic()
    roadmap = build_roadmap(z1, z2, a, RoadmapConfig(metric="inf", w_eps=1.5))
    roadmap.save(tmp_path / "lsr")
    assert sorted(p.name for p in (tmp_path / "lsr").iterdir()) == [
        "MANIFEST.json",  # the sha256 of the other two, written last
        "roadmap.json",
        "roadmap.safetensors",
    ]
    loaded = Roadmap.load(tmp_path / "lsr")
    assert loaded.config == roadmap.config
    assert (loaded.epsilon, loaded.mu0, loaded.sigma0) == (
        roadmap.epsilon,
        roadmap.mu0,
        roadmap.sigma0,
    )
    assert loaded.stats == roadmap.stats
    for key in rm._ARRAY_KEYS:
        want, got = getattr(roadmap, key), getattr(loaded, key)
        assert got.dtype == want.dtype and np.array_equal(got, want), key
    assert loaded.shortest_paths(0, 7) == roadmap.shortest_paths(0, 7)
    assert loaded.nearest_node(z1[0]) == roadmap.nearest_node(z1[0])
    assert loaded.whitening.shape == (8, 8)
    assert np.array_equal(loaded.whitening, roadmap.whitening)


def test_load_broken_folder(tmp_path):
    z1, z2, a, _ = synthetic()
    good = tmp_path / "good"
    build_roadmap(z1, z2, a).save(good)
    meta = json.loads((good / "roadmap.json").read_text())
    arrays = load_file(str(good / "roadmap.safetensors"))

    def broken(name, meta=meta, arrays=arrays, raw_json=None):
        folder = tmp_path / name
        folder.mkdir()
        (folder / "roadmap.json").write_text(raw_json or json.dumps(meta))
        if arrays is not None:
            save_file(arrays, str(folder / "roadmap.safetensors"))
        return folder

    cases = {
        "no such roadmap folder": tmp_path / "absent",
        "roadmap.safetensors: missing": broken("no_arrays", arrays=None),
        "not readable JSON": broken("bad_json", raw_json="{nope"),
        "expected format": broken("bad_format", meta={**meta, "format": "other"}),
        "missing epsilon": broken("no_eps", meta={k: v for k, v in meta.items() if k != "epsilon"}),
        "bad config": broken("bad_config", meta={**meta, "config": {"metric": "l7"}}),
        "missing arrays edges": broken(
            "no_edges", arrays={k: v for k, v in arrays.items() if k != "edges"}
        ),
        "edges must be pairs": broken(
            "bad_edges", arrays={**arrays, "edges": arrays["edges"] + 100}
        ),
        "nodes must be a 2-D float32": broken(
            "bad_nodes", arrays={**arrays, "nodes": arrays["nodes"].astype(np.float64)}
        ),
        "edge_weights must have shape": broken(
            "bad_weights", arrays={**arrays, "edge_weights": arrays["edge_weights"][:-1]}
        ),
    }
    (tmp_path / "no_json").mkdir()
    cases["roadmap.json: missing"] = tmp_path / "no_json"
    corrupt = broken("corrupt")
    (corrupt / "roadmap.safetensors").write_bytes(b"\x00" * 10)
    cases["not a readable safetensors"] = corrupt
    for message, folder in cases.items():
        with pytest.raises(RoadmapError, match=message):
            Roadmap.load(folder)


# ------------------------------------------------------------------------------------------
# The reference release's latents (paper's box-stacking data), when present
# ------------------------------------------------------------------------------------------


def test_reference_latents_give_the_reference_roadmap():
    if not REFERENCE.is_file():
        pytest.skip(f"reference latents not found at {REFERENCE}")
    data = np.load(REFERENCE)
    roadmap = build_roadmap(
        data["z1"],
        data["z2"],
        data["action"],
        RoadmapConfig(metric="l1", w_eps=1.0, min_samples=3, eps_rule="paper"),
    )
    stats = roadmap.stats
    assert roadmap.epsilon == pytest.approx(1.44686, rel=1e-4)
    assert stats["regions_before_pruning"] == 307
    assert stats["edges_before_pruning"] == 592
    assert stats["edge_weight_before_pruning"] == 3229
    assert (roadmap.num_nodes, len(roadmap.edges)) == (288, 573)
    assert (stats["nodes"], stats["edges"]) == (288, 573)


def test_twins_are_one_node_to_paths_and_supports(tmp_path):
    # 0 - 1   2 - 3, and 1, 2 one state: 0 - {1, 2} - 3
    roadmap = make_roadmap([(0, 0), (1, 0), (5, 5), (6, 5)], [(0, 1), (2, 3)])
    roadmap.edge_weights[:] = [4, 7]
    assert roadmap.shortest_paths(0, 3) == []
    twinned = replace(roadmap, twins=np.array([[1, 2]], np.int64))
    assert twinned.shortest_paths(0, 3) == [[0, 1, 3]]  # passes the group by its first node
    assert twinned.shortest_paths(3, 0) == [[3, 1, 0]]
    assert twinned.shortest_paths(0, 2) == [[0, 2]]  # arrives at dst itself
    assert twinned.shortest_paths(2, 1) == [[2]]  # one state: at the goal
    assert twinned.supports([0, 1, 3]) == twinned.supports([0, 2, 3]) == [4, 7]
    assert twinned.neighbours(2) == twinned.neighbours(1) == [0, 3]
    assert twinned.twin_group.tolist() == [0, 1, 1, 3]
    assert twinned.group_edges.tolist() == [[0, 1], [1, 3]]  # the steps plans take
    twinned.save(tmp_path / "twinned")
    assert Roadmap.load(tmp_path / "twinned").twins.tolist() == [[1, 2]]
    roadmap.save(tmp_path / "plain")  # no twins: the file is as before growth
    assert "twins" not in load_file(str(tmp_path / "plain" / ARRAYS_NAME))
    with pytest.raises(RoadmapError, match="not an edge"):
        twinned.supports([0, 1, 2, 3])  # a step between twins is no move
    for bad in ([[2, 1]], [[1, 4]], [[1, 2], [0, 1]]):
        with pytest.raises(RoadmapError, match="twins"):
            replace(roadmap, twins=np.array(bad, np.int64))
    for joined in ([[0, 1]], [[0, 2], [1, 2]]):  # an edge inside a group, directly or by a chain
        with pytest.raises(RoadmapError, match=r"joined by an edge: edge \(0, 1\)"):
            replace(roadmap, twins=np.array(joined, np.int64))


def test_the_stable_rule_takes_the_finest_flat_range_not_a_longer_coarse_one():
    # 40 states in 4 groups far apart, every move from one group to the next: the 4 groups
    # stay flat over a longer range of epsilon than the 40 states, and no action pair ever
    # falls inside a group (box stacking's stack-height profiles). The states are the roadmap.
    rng = np.random.default_rng(5)
    groups = np.repeat(rng.normal(0.0, 1.0, size=(4, 8)) * 400, 10, axis=0)
    centres = groups + rng.normal(0.0, 1.0, size=(40, 8)) * 3
    order = np.arange(40)
    nxt = (order + 10) % 40  # the same place in the next group
    noise = np.eye(8)[0] * 0.3
    z1 = np.r_[centres, centres, centres + noise]
    z2 = np.r_[centres + noise, centres[nxt], centres]
    a = np.r_[np.zeros(40), np.ones(40), np.zeros(40)].astype(np.int8)
    roadmap = build_roadmap(z1, z2, a, RoadmapConfig(min_samples=1))
    assert roadmap.stats["eps_rule"] == "stable"
    assert roadmap.stats["regions_before_pruning"] == 40
