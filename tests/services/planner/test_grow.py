from dataclasses import replace

import numpy as np
import pytest

from services.planner.exits import action_exits
from services.planner.grow import (
    contradictions,
    fresh_regions,
    grow,
    same_state_radius,
    twin_links,
)
from services.planner.knowing import calibrate
from services.planner.members import Members
from services.planner.roadmap import RoadmapConfig, build_roadmap, fit_whitening, pair_distances
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
        errors=np.full((len(points), 3), 0.01, np.float32),
        actions=u,
        a=(u[:, 0] >= 0).astype(np.uint8),
        states=np.zeros((len(points), 0), np.int8),
        has_state=np.zeros(len(points), np.uint8),
        experience=np.zeros(len(rows), np.uint8),
        keys=np.zeros(len(rows), np.uint64),
    )


def base(rows: list[tuple[str, str, int]]):
    m = members(rows, seed=0)
    config = RoadmapConfig(metric="l1", eps_rule="paper", w_eps=30.0, min_samples=1)
    roadmap = build_roadmap(m.points[0::2], m.points[1::2], m.a, config)
    return roadmap, calibrate(roadmap, m.points, m.errors), m


BASE = [("A", "A", 0), ("B", "B", 0), ("C", "C", 0), ("D", "D", 0)] * 3 + [
    ("A", "B", 1),
    ("C", "D", 2),
]


def test_points_no_node_holds_form_regions_of_at_least_the_threshold():
    points = np.array([[0.0], [10.0], [20.0], [20.5], [21.0], [40.0], [40.5]])
    regions = fresh_regions(points, np.arange(2, 7), epsilon=1.0, metric="l1", min_new=3)
    assert [r.tolist() for r in regions] == [[2, 3, 4]]  # 40 and 40.5: too few


def test_growth_adds_the_edges_experience_shows_and_keeps_the_built_nodes():
    roadmap, known, m = base(BASE)
    assert roadmap.num_nodes == 4 and len(roadmap.edges) == 2
    experience = members([("B", "C", 3), ("A", "A", 4), ("far", "far", 5)], seed=1)
    grown, _, everything, report = grow(roadmap, known, m, experience, TASK)
    assert np.array_equal(grown.nodes[:4], roadmap.nodes)  # old nodes keep ids and latents
    # the spread within nodes is fitted again over the images they hold now
    assert roadmap.whitening.shape == grown.whitening.shape == (2, 2)
    assert np.array_equal(grown.whitening, fit_whitening(everything.points, grown.point_node))
    assert not np.array_equal(grown.whitening, roadmap.whitening)
    assert len(grown.edges) == 3 and report["components"] == [2, 1]
    assert report["new_edges"] == 1 and report["no_change"] == 1
    assert report["held_for_review"] == 1 and report["held"].tolist() == [2]
    assert report["new_nodes"] == 0  # two images far away are no state yet
    assert len(everything.points) == len(m.points) + 6 == len(grown.point_node)


def test_a_roadmap_built_with_exits_keeps_them_for_experience_too():
    roadmap, known, m = base(BASE)
    experience = members([("B", "C", 3)], seed=1)
    assert len(grow(roadmap, known, m, experience, TASK)[0].exits) == 0  # built without
    exits = action_exits(roadmap.point_node, m.a, m.actions, TASK.same_action)
    roadmap = replace(roadmap, exits=exits)
    grown = grow(roadmap, known, m, experience, TASK)[0]
    b, c = grown.point_node[-2:]
    rows = sorted(map(tuple, grown.exits.tolist()))
    assert rows == sorted([*map(tuple, exits.tolist()), (b, c, 2)])  # a third move, B to C


def test_an_edge_contradicted_more_than_supported_is_flagged_and_kept():
    roadmap, known, m = base(BASE)
    # Action 1 took A to B once in the data; experience executes it from A three times and
    # sees C each time.
    experience = members([("A", "C", 1)] * 3, seed=2)
    grown, _, _, report = grow(roadmap, known, m, experience, TASK)
    a, b, c = (int(roadmap.nearest_node(np.array([CENTRES[x], 0.0]))) for x in "ABC")
    edges = {tuple(e) for e in grown.edges.tolist()}
    assert (min(a, b), max(a, b)) in edges and (min(a, c), max(a, c)) in edges
    assert report["flagged_edges"] == [[min(a, b), max(a, b), 3, 1]]
    assert report["contradictions"] == 3


def test_contradictions_need_the_same_action():
    roadmap, _, m = base(BASE)
    experience = members([("A", "C", 7)], seed=3)  # another action from A: no contradiction
    everything = m + experience
    joined = [roadmap.nearest_node(p) for p in experience.points]
    node = np.concatenate([roadmap.point_node, joined])
    assert contradictions(TASK, node, everything, np.array([len(m.a)]), 1.0, "l1") == {}


def test_an_outcome_in_another_node_of_the_same_state_is_no_contradiction():
    """Twins: action 1 from A led to B in the data; executed again it lands in another node
    whose image lies within the same-state radius of B's: not a contradiction. Farther: one."""
    roadmap, _, m = base(BASE)
    twin = roadmap.num_nodes  # a node id the experience's image is said to be in
    for offset, expected in ((0.3, 0), (5.0, 1)):
        experience = members([("A", "B", 1)], seed=3)
        experience.points[1] += offset
        everything = m + experience
        node = np.concatenate([roadmap.point_node, [roadmap.nearest_node(experience.points[0])]])
        node = np.concatenate([node, [twin]])
        found = contradictions(TASK, node, everything, np.array([len(m.a)]), 1.0, "l1")
        assert sum(found.values()) == expected


def test_the_same_state_radius_lies_between_one_look_and_one_move():
    _, _, m = base(BASE)
    radius = same_state_radius(m, "l1", fallback=-1.0)
    still = pair_distances(m.points[0::2], m.points[1::2], "l1")[m.a == 0]
    assert still.max() < radius < 10.0  # A-B and C-D, one move each, lie 10 apart
    no_pairs = replace(m, a=np.ones_like(m.a))
    assert same_state_radius(no_pairs, "l1", fallback=-1.0) == -1.0


def test_an_image_known_at_a_node_but_near_none_of_its_images_does_not_join_it():
    """3 away from B: within B's knowing bound, but B's images lie within 0.2 of each other and
    one move is 10: another state. Three such images linked to D by an action make a node."""
    roadmap, known, m = base(BASE)
    wide = replace(known, node_thresholds=(50.0,) * roadmap.num_nodes)
    experience = members([("D", "B", 6)] * 4, seed=4)
    experience.points[1::2] += np.array([3.0, 0.0], np.float32)  # every "after" image
    grown, _, _, report = grow(roadmap, wide, m, experience, TASK)
    assert report["images_known_elsewhere"] == 4 and report["new_nodes"] == 1
    b = int(roadmap.nearest_node(np.array([CENTRES["B"], 0.0])))
    assert not np.isin(grown.point_node[len(m.points) :][1::2], [b]).any()


def test_repeated_new_images_linked_by_an_action_make_a_node():
    roadmap, known, m = base(BASE)
    experience = members([("D", "far", 6)] * 3 + [("far", "far", 0)], seed=4)
    grown, grown_known, _, report = grow(roadmap, known, m, experience, TASK)
    assert report["new_nodes"] == 1 and grown.num_nodes == 5
    assert report["held_for_review"] == 0
    assert grown_known.node_thresholds[:4] == known.node_thresholds  # built nodes as before
    assert len(grown_known.node_thresholds) == 5


@pytest.mark.parametrize("rows", [[("A", "B", 1)]])
def test_members_add_keeps_order(rows):
    first, second = members(rows, 0), members(rows, 1)
    both = first + second
    assert np.array_equal(both.points[2:], second.points) and len(both.a) == 2


def test_each_contradicting_tuple_counts_once_however_many_pairs_support_the_edge():
    roadmap, known, m = base(BASE + [("A", "B", 1)] * 4)  # A-B by action 1, five times
    grown, _, _, report = grow(roadmap, known, m, members([("A", "C", 1)] * 2, seed=5), TASK)
    assert report["contradictions"] == 2 and not report["flagged_edges"]
    assert len(grown.edges) == 3  # A-B stays, A-C joins


def test_members_without_states_join_members_with_them_either_way_round():
    stateless = members([("A", "B", 1)], seed=0)
    stated = replace(
        stateless,
        states=np.ones((2, 5), np.int8),
        has_state=np.ones(2, np.uint8),
    )
    for both in (stateless + stated, stated + stateless):
        assert both.states.shape == (4, 5) and both.has_state.sum() == 2


def test_a_no_action_pair_across_two_nodes_makes_them_twins_unless_an_edge_joins_them():
    roadmap, known, m = base(BASE)
    a, b, c, d = (int(roadmap.nearest_node(np.array([CENTRES[x], 0.0]))) for x in "ABCD")
    assert roadmap.shortest_paths(a, d) == []
    # B and C looked alike once (one state, two nodes); A and B too, but a move joins them.
    experience = members([("B", "C", 0), ("A", "B", 0)], seed=3)
    grown, _, everything, report = grow(roadmap, known, m, experience, TASK)
    assert grown.twins.tolist() == [[min(b, c), max(b, c)]]
    assert report["twins"] == [0, 1] and report["twins_refused"] == 1
    assert report["components"] == [2, 1]
    (path,) = grown.shortest_paths(a, d)
    assert len(path) == 3 and path[0] == a and path[-1] == d and path[1] in (b, c)
    again, _, _, report = grow(grown, known, everything, members([("D", "D", 0)], seed=4), TASK)
    assert again.twins.tolist() == grown.twins.tolist() and report["twins"] == [1, 1]


def test_a_twin_link_is_refused_when_a_chain_of_twins_would_hold_an_edge():
    # no-action pairs 0~1 and 1~2, a move 0 - 2: linking 1~2 would make 0 and 2 one state
    node = np.array([0, 1, 1, 2, 0, 2])
    twins, refused = twin_links(node, np.array([0, 0, 1]), np.array([[0, 2]]), np.zeros((0, 2)), 3)
    assert twins.tolist() == [[0, 1]] and refused == 1
    known = np.array([[1, 2]])  # a link kept before is kept, and refuses the new one instead
    twins, refused = twin_links(node, np.array([0, 0, 1]), np.array([[0, 2]]), known, 3)
    assert twins.tolist() == [[1, 2]] and refused == 1


def test_an_image_without_a_node_joins_its_no_action_partners_node():
    """Phase 1: a no-action pair is one state seen twice, however far apart the two looks."""
    roadmap, known, m = base(BASE)
    wide = replace(known, node_thresholds=(50.0,) * roadmap.num_nodes)
    # B looked at twice, the second look 3 away; and a new state seen from D twice, looked at
    # again 5 away (a region of two close images and one far look, held together by the pair)
    experience = members([("B", "B", 0), ("D", "far", 6), ("D", "far", 6), ("far", "far", 0)], 5)
    experience.points[1] += np.array([3.0, 0.0], np.float32)
    experience.points[7] += np.array([5.0, 0.0], np.float32)
    grown, _, _, report = grow(roadmap, wide, m, experience, TASK)
    b = int(roadmap.nearest_node(np.array([CENTRES["B"], 0.0])))
    new = grown.point_node[len(m.points) :]
    assert report["images_joined_by_partner"] == 1 and new[1] == b
    assert report["new_nodes"] == 1 and (new[[3, 5, 6, 7]] == roadmap.num_nodes).all()
    assert report["held_for_review"] == 0


def test_members_kept_before_tuple_keys_load_with_keys_unknown(tmp_path):
    from safetensors.numpy import load_file, save_file

    from services.planner.members import MEMBERS

    kept = members([("A", "B", 1), ("B", "B", 0)], seed=0)
    kept.save(tmp_path)
    arrays = load_file(str(tmp_path / MEMBERS))
    del arrays["keys"]
    save_file(arrays, str(tmp_path / MEMBERS))
    assert Members.load(tmp_path).keys.tolist() == [0, 0]


def test_members_missing_or_broken_are_named(tmp_path):
    from services.planner.members import MEMBERS
    from services.planner.roadmap import RoadmapError

    with pytest.raises(RoadmapError, match=f"{MEMBERS}: missing"):
        Members.load(tmp_path)
    (tmp_path / MEMBERS).write_bytes(b"\x00" * 8)
    with pytest.raises(RoadmapError, match="not a readable safetensors file"):
        Members.load(tmp_path)


def test_members_of_an_older_knowing_ask_for_calibration(tmp_path):
    from safetensors.numpy import load_file, save_file

    from services.planner.members import MEMBERS
    from services.planner.roadmap import RoadmapError

    members([("A", "B", 1), ("B", "B", 0)], seed=0).save(tmp_path)
    arrays = load_file(str(tmp_path / MEMBERS))
    arrays["errors"] = arrays["errors"][:, :2].copy()  # whole image and worst patch: v4's
    save_file(arrays, str(tmp_path / MEMBERS))
    with pytest.raises(RoadmapError, match=r"2 reconstruction errors a point.*lsr calibrate"):
        Members.load(tmp_path)
