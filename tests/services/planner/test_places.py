from dataclasses import replace

import numpy as np

from services.planner.knowing import calibrate, keep_place
from services.planner.members import Members
from services.planner.places import Places
from services.planner.roadmap import RoadmapConfig, build_roadmap

# Two look-alike regions 1 apart in 2-D (L1), each of 12 points spread 0.2 along y: knowing
# (twice a high quantile, here widened) reaches across, Algorithm 1's epsilon does not.
CENTRES = np.array([[0.0, 0.0], [1.0, 0.0]])


def roadmap_and_members():
    rng = np.random.default_rng(0)
    z1, z2 = [], []
    for centre in CENTRES:
        for _ in range(6):  # no-action pairs
            z1.append(centre + np.array([0.0, rng.uniform(-0.1, 0.1)]))
            z2.append(centre + np.array([0.0, rng.uniform(-0.1, 0.1)]))
    z1.append(CENTRES[0])  # one action pair between them
    z2.append(CENTRES[1])
    a = np.array([0] * 12 + [1])
    config = RoadmapConfig(metric="l1", eps_rule="paper", w_eps=1.0, min_samples=1)
    roadmap = build_roadmap(np.array(z1), np.array(z2), a, config)
    points = np.stack([z1, z2], 1).reshape(-1, 2).astype(np.float32)
    calibration = calibrate(roadmap, points, np.full((len(points), 3), 1e-3))
    wide = replace(calibration, node_thresholds=(5.0, 5.0))  # each node knows the other's images
    return roadmap, wide, points


def test_a_loop_that_went_to_the_look_alike_plans_from_where_it_is():
    roadmap, wide, points = roadmap_and_members()
    places = Places(points.astype(np.float64), roadmap.point_node, roadmap.epsilon, "l1")
    assert roadmap.num_nodes == 2 and 0 < roadmap.epsilon < 0.5
    here = roadmap.nearest_node(CENTRES[1])
    there = 1 - here
    image = CENTRES[1] + np.array([0.0, 0.05])  # an image of the look-alike, known at both nodes
    assert keep_place(roadmap, wide, image, here, there) == there  # knowing alone: stays
    assert keep_place(roadmap, wide, image, here, there, places) == here
    # an image between the two, near neither's points: the loop keeps its place
    between = np.array([0.5, 0.0])
    start = roadmap.nearest_node(between)
    assert keep_place(roadmap, wide, between, start, 1 - start, places) == 1 - start


def test_places_load_from_the_roadmaps_members_or_not_at_all(tmp_path):
    roadmap, _, points = roadmap_and_members()
    assert Places.load(tmp_path, roadmap) is None  # an older model: no members kept
    n = len(points)
    Members(
        points=points,
        errors=np.zeros((n, 3), np.float32),
        actions=np.full((n // 2, 1), -1, np.int8),
        a=np.zeros(n // 2, np.uint8),
        states=np.zeros((n, 0), np.int8),
        has_state=np.zeros(n, np.uint8),
        experience=np.zeros(n // 2, np.uint8),
        keys=np.zeros(n // 2, np.uint64),
    ).save(tmp_path)
    places = Places.load(tmp_path, roadmap)
    assert places is not None and places.holds(CENTRES[0], roadmap.nearest_node(CENTRES[0]))
    assert not places.holds(np.array([0.5, 0.0]), 0) and not places.holds([0.5, 0.0], 1)
    other = replace(roadmap, point_node=roadmap.point_node[:-2])  # members of another build
    assert Places.load(tmp_path, other) is None
    (tmp_path / "members.safetensors").write_bytes(b"not safetensors")
    assert Places.load(tmp_path, roadmap) is None
