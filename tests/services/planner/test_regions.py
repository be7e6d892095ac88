import numpy as np
import pytest
from scipy.sparse.csgraph import connected_components

from services.planner import regions as rg
from services.planner.regions import (
    RoadmapError,
    connected_regions,
    metric_p,
    pair_distances,
    stable_epsilon,
)

METRICS = ["l1", "l2", "inf"]


# ------------------------------------------------------------------------------------------
# Phase 2 against the definition
# ------------------------------------------------------------------------------------------


def brute_force_regions(points, eps, metric, strict=True):
    """Algorithm 1's phase 2 by definition: components of the graph d(p, q) < eps."""
    diff = np.abs(points[:, None, :] - points[None, :, :])
    if metric == "l1":
        dist = diff.sum(-1)
    elif metric == "l2":
        dist = np.sqrt((diff**2).sum(-1))
    else:
        dist = diff.max(-1)
    _, labels = connected_components(dist < eps if strict else dist <= eps, directed=False)
    _, first = np.unique(labels, return_index=True)
    rank = np.empty(len(first), dtype=np.int64)
    rank[np.argsort(first)] = np.arange(len(first))  # numbered by smallest point index
    return rank[labels]


def grid_points(seed):
    """Points on a half-integer grid: many pairs lie at exactly eps = 0.5 or 1, in every metric."""
    rng = np.random.default_rng(seed)
    return rng.integers(0, 12, size=(300, 3)) * 0.5


def clustered_points(seed):
    """Clusters of different spread in 8-D, some touching, some chained, some not."""
    rng = np.random.default_rng(seed)
    centres = rng.normal(0.0, 1.0, size=(25, 8))
    spread = rng.uniform(0.05, 0.35, size=25)
    cls = rng.integers(0, 25, size=500)
    return centres[cls] + rng.normal(size=(500, 8)) * spread[cls, None]


def chain_points():
    """Stars joined only through members (neither leader is within eps of the other star)."""
    line = np.array([0.0, 2.7, 0.9, 1.8, 10.0, 12.5, 11.0, 11.5])
    return np.stack([line, np.zeros_like(line)], axis=1)


@pytest.mark.parametrize("metric", METRICS)
@pytest.mark.parametrize("sample", [16, None])
def test_regions_match_brute_force(metric, sample, monkeypatch):
    if sample is not None:  # many rounds of the coarse cover
        monkeypatch.setattr(rg, "_COARSE_SAMPLE", sample)
    cases = [(grid_points(1), 1.0), (grid_points(2), 0.5), (grid_points(2), 1.0)]
    pts = clustered_points(3)
    near = pair_distances(pts[:-1], pts[1:], metric)
    cases += [(pts, float(np.quantile(near, q))) for q in (0.05, 0.2, 0.5)]
    for points, eps in cases:
        labels, info = connected_regions(points, eps, metric)
        expected = brute_force_regions(points, eps, metric)
        assert np.array_equal(labels, expected), (metric, eps, info)
    # The grids have pairs at exactly eps: there '<' and '<=' give different partitions.
    for points, eps in cases[:3]:
        strict = brute_force_regions(points, eps, metric)
        assert 10 < strict.max() < len(points) - 10
        assert not np.array_equal(strict, brute_force_regions(points, eps, metric, False))


@pytest.mark.parametrize("metric", METRICS)
def test_regions_joined_through_members(metric):
    labels, info = connected_regions(chain_points(), 1.0, metric)
    assert labels.tolist() == [0, 0, 0, 0, 1, 2, 3, 3]  # 10 | 11 and 11.5 | 12.5: exactly eps
    assert info["star_joins"] >= 1  # settled by comparing members, not leaders
    assert np.array_equal(labels, brute_force_regions(chain_points(), 1.0, metric))


def test_regions_distance_exactly_eps_is_not_joined():
    points = np.array([[0.0, 0.0], [3.0, 4.0], [6.0, 8.0]])
    assert connected_regions(points, 5.0, "l2")[0].tolist() == [0, 1, 2]
    assert connected_regions(points, np.nextafter(5.0, 6.0), "l2")[0].tolist() == [0, 0, 0]
    assert connected_regions(points, 7.0, "l1")[0].tolist() == [0, 1, 2]
    assert connected_regions(points, 4.0, "inf")[0].tolist() == [0, 1, 2]
    assert connected_regions(points, 0.0, "l1")[0].tolist() == [0, 1, 2]
    assert connected_regions(np.zeros((0, 2)), 1.0, "l1")[0].shape == (0,)


def test_metric_helpers():
    assert [metric_p(m) for m in METRICS] == [1.0, 2.0, np.inf]
    a = np.array([[0.0, 0.0], [1.0, 1.0]])
    b = np.array([[3.0, 4.0], [1.0, 1.0]])
    assert pair_distances(a, b, "l1").tolist() == [7.0, 0.0]
    assert pair_distances(a, b, "l2").tolist() == [5.0, 0.0]
    assert pair_distances(a, b, "inf").tolist() == [4.0, 0.0]
    assert pair_distances(a[0], b[0], "l2") == 5.0
    assert pair_distances(a, b[:1], "l1").tolist() == [7.0, 5.0]  # broadcasts
    with pytest.raises(RoadmapError, match="broadcast"):
        pair_distances(a, np.zeros((3, 2)), "l1")
    with pytest.raises(RoadmapError):
        metric_p("l0")


# ------------------------------------------------------------------------------------------
# Choosing epsilon from the data
# ------------------------------------------------------------------------------------------


def sparse_classes(seed=0, classes=30, per_class=4, dim=16):
    """Few points a class: any two members 0.5-1.5 apart, classes at least ~8 apart."""
    rng = np.random.default_rng(seed)
    centres = rng.normal(size=(classes, dim)) * 6.0
    labels = np.repeat(np.arange(classes), per_class)
    points = centres[labels] + rng.uniform(-0.25, 0.25, size=(len(labels), dim))
    return points, labels


def test_stable_epsilon_recovers_sparse_classes():
    points, labels = sparse_classes()
    order = np.random.default_rng(2).permutation(len(points))
    points, labels = points[order], labels[order]  # pairs (2i, 2i + 1) of random points
    pairs = np.arange(len(points) // 2)
    same = labels[0::2] == labels[1::2]
    eps, info = stable_epsilon(points, pairs[same], pairs[~same], "l1")
    assert eps is not None and info["range"][0] < eps < info["range"][1]
    assert info["regions"] == sorted(info["regions"], reverse=True)  # coarser as eps grows
    found, _ = connected_regions(points, eps, "l1")
    assert found.max() + 1 == 30
    assert all(len(np.unique(labels[found == r])) == 1 for r in range(30))  # every region pure
    # The paper's epsilon (mu0 + sigma0) is below most in-class distances here: it splits.
    d_still = pair_distances(points[0::2][same], points[1::2][same], "l1")
    split, _ = connected_regions(points, d_still.mean() + d_still.std(), "l1")
    assert split.max() + 1 > 30


def test_stable_epsilon_stops_where_whole_states_chain():
    """Two of 12 states lie closer than the rest (a VAE from little data): they join soon after
    each state's last pieces do, before any range is flat, and no action pair says so; the
    scan stops at that join and epsilon lies between it and the joined no-action pairs."""
    for seed in range(5):
        rng = np.random.default_rng(seed)
        centres = rng.normal(size=(12, 4)) * 30.0
        centres[1] = centres[0] + [2.0, 0, 0, 0]
        labels = np.repeat(np.arange(12), 20)
        points = centres[labels] + rng.uniform(0, 1, size=(240, 4)) * [0.5, 1, 1, 1]
        order = rng.permutation(240)
        points, labels = points[order], labels[order]
        first, second = labels[0::2], labels[1::2]
        pairs = np.arange(120)
        close = np.minimum(first, second) + np.maximum(first, second) == 1  # states 0 and 1
        eps, info = stable_epsilon(
            points, pairs[first == second], pairs[~close & (first != second)], "l1"
        )
        assert info["stop"] == "whole regions join"
        assert info["joined"] <= eps <= info["grid"][-2]
        found, _ = connected_regions(points, eps, "l1")
        assert found.max() + 1 == 12
        assert all(len(np.unique(labels[found == r])) == 1 for r in range(12))
        # past the stop, a long flat range of 11 regions: the two states as one
        assert connected_regions(points, 4 * eps, "l1")[0].max() + 1 == 11


def test_stable_epsilon_gives_up_without_structure():
    rng = np.random.default_rng(1)
    points = rng.uniform(size=(200, 3))  # no classes: the region count never levels off
    points[1:100:2] = points[0:100:2] + rng.uniform(0, 0.01, size=(50, 3))  # 50 still pairs
    eps, info = stable_epsilon(points, np.arange(50), np.arange(50, 100), "l1")
    assert eps is None and len(info["regions"]) == len(info["grid"]) > 0
    still = np.arange(3)
    assert stable_epsilon(np.zeros((6, 2)), still, still, "l1")[0] is None  # mu0 = 0: no scale
