import numpy as np
import pytest

from services.planner.grow import contradictions, grow, regions
from services.planner.members import Members
from services.planner.roadmap import RoadmapConfig, build_roadmap
from shared.tasks import get_task

TASK = get_task("box_stacking")
CENTRES = {"A": 0.0, "B": 10.0, "C": 20.0, "D": 30.0, "far": 90.0}


def latent(name: str, rng: np.random.Generator) -> np.ndarray:
    return np.array([CENTRES[name], 0.0]) + rng.normal(0, 0.05, 2)


def members(rows: list[tuple[str, str, int]], seed: int) -> Members:
    """Tuples (from, to, action id): action id 0 is a no-action pair, k > 0 an action."""
    rng = np.random.default_rng(seed)
    points = np.array([latent(x, rng) for a, b, _ in rows for x in (a, b)], np.float32)
    u = np.array([[k, k, k, k] if k else [-1] * 4 for *_, k in rows], np.int8)
    return Members(
        points=points,
        errors=np.zeros((len(points), 2), np.float32),
        actions=u,
        a=(u[:, 0] >= 0).astype(np.uint8),
        states=np.zeros((len(points), 0), np.int8),
        has_state=np.zeros(len(points), np.uint8),
    )


def base(rows: list[tuple[str, str, int]]):
    m = members(rows, seed=0)
    config = RoadmapConfig(metric="l1", eps_rule="paper", w_eps=30.0, min_samples=1)
    return build_roadmap(m.points[0::2], m.points[1::2], m.a, config), m


BASE = [("A", "A", 0), ("B", "B", 0), ("C", "C", 0), ("D", "D", 0)] * 3 + [
    ("A", "B", 1),
    ("C", "D", 2),
]


def test_regions_join_new_points_and_merge_the_nodes_they_bridge():
    points = np.array([[0.0], [10.0], [0.9], [1.8], [5.0], [20.0], [20.5], [21.0]])
    built = np.array([0, 1, -1, -1, -1, -1, -1, -1])
    node, became, fresh = regions(points, built, 2, epsilon=1.0, metric="l1", min_new=3)
    assert node.tolist()[:5] == [0, 1, 0, 0, -1]  # 1.8 joins through 0.9; 5.0 joins nothing
    assert became.tolist() == [0, 1] and [f.tolist() for f in fresh] == [[5, 6, 7]]
    assert node.tolist()[5:] == [2, 2, 2]  # a candidate new node
    bridged = np.array([[0.0], [2.0], [1.0]])
    node, became, fresh = regions(bridged, np.array([0, 1, -1]), 2, 1.5, "l1", 3)
    assert node.tolist() == [0, 0, 0] and became.tolist() == [0, 0] and not fresh


def test_growth_adds_the_edges_experience_shows_and_keeps_the_built_nodes():
    roadmap, m = base(BASE)
    assert roadmap.num_nodes == 4 and len(roadmap.edges) == 2
    experience = members([("B", "C", 3), ("A", "A", 4), ("far", "far", 5)], seed=1)
    grown, everything, report = grow(roadmap, m, experience, TASK)
    assert np.array_equal(grown.nodes[:4], roadmap.nodes)  # old nodes keep ids and latents
    assert len(grown.edges) == 3 and report["components"] == [2, 1]
    assert report["new_edges"] == 1 and report["no_change"] == 1
    assert report["held_for_review"] == 1 and report["held"].tolist() == [2]
    assert report["new_nodes"] == 0  # two images far away are no state yet
    assert len(everything.points) == len(m.points) + 6 == len(grown.point_node)


def test_an_edge_contradicted_more_than_supported_is_dropped():
    roadmap, m = base(BASE)
    # Action 1 took A to B once in the data; experience executes it from A three times and
    # sees C each time.
    experience = members([("A", "C", 1)] * 3, seed=2)
    grown, _, report = grow(roadmap, m, experience, TASK)
    a, b, c = (int(roadmap.nearest_node(np.array([CENTRES[x], 0.0]))) for x in "ABC")
    edges = {tuple(e) for e in grown.edges.tolist()}
    assert (min(a, b), max(a, b)) not in edges and (min(a, c), max(a, c)) in edges
    assert report["dropped_edges"] == [[min(a, b), max(a, b)]]
    assert report["contradictions"] == 3


def test_contradictions_need_the_same_action():
    roadmap, m = base(BASE)
    experience = members([("A", "C", 7)], seed=3)  # another action from A: no contradiction
    everything = m + experience
    joined = [roadmap.nearest_node(p) for p in experience.points]
    node = np.concatenate([roadmap.point_node, joined])
    assert contradictions(TASK, node, everything, np.array([len(m.a)])) == {}


def test_repeated_new_images_linked_by_an_action_make_a_node():
    roadmap, m = base(BASE)
    experience = members([("D", "far", 6)] * 3 + [("far", "far", 0)], seed=4)
    grown, _, report = grow(roadmap, m, experience, TASK)
    assert report["new_nodes"] == 1 and grown.num_nodes == 5
    assert report["held_for_review"] == 0


@pytest.mark.parametrize("rows", [[("A", "B", 1)]])
def test_members_add_keeps_order(rows):
    first, second = members(rows, 0), members(rows, 1)
    both = first + second
    assert np.array_equal(both.points[2:], second.points) and len(both.a) == 2


def test_images_bridging_two_nodes_merge_them_as_building_on_all_the_data_would():
    roadmap, m = base(BASE)
    step = roadmap.epsilon / 2
    chain = np.arange(CENTRES["A"] + step, CENTRES["B"], step)
    if len(chain) % 2:  # pairs of points
        chain = np.append(chain, chain[-1])
    points = np.stack([chain, np.zeros_like(chain)], axis=1).astype(np.float32)
    n = len(points) // 2
    bridge = Members(
        points=points,
        errors=np.zeros((2 * n, 2), np.float32),
        actions=np.full((n, 4), -1, np.int8),
        a=np.zeros(n, np.uint8),
        states=np.zeros((2 * n, 0), np.int8),
        has_state=np.zeros(2 * n, np.uint8),
    )
    grown, _, report = grow(roadmap, m, bridge, TASK)
    assert report["merged_nodes"] == 1 and grown.num_nodes == 3
    a, b = (roadmap.nearest_node(np.array([CENTRES[x], 0.0])) for x in "AB")
    assert grown.nearest_node(roadmap.nodes[a]) == grown.nearest_node(roadmap.nodes[b])
    assert report["components"] == [2, 2] and len(grown.edges) == 1  # A-B became one node
