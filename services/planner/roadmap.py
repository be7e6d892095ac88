"""The Latent Space Roadmap (LSR, paper Algorithm 1): build it, query it, save and load it.

Phase 1 numbers the latents z1[0], z2[0], z1[1], z2[1], ... and keeps the action pairs as the
reference edges. Phase 2 groups the latents into valid regions: the connected components of the
graph joining two latents whose distance is strictly below epsilon. Phase 3 makes one node per
region (the member closest to the region mean) and one edge per pair of regions that an action
pair joins, weighted by the number of such action pairs. Small regions and then isolated nodes
are pruned.

Phase 2 is exact (the same partition as comparing every pair of latents) but never compares every
pair; see `connected_regions`.
"""

from __future__ import annotations

import json
import math
import operator
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from safetensors.numpy import load_file, save_file
from scipy import sparse
from scipy.sparse.csgraph import shortest_path
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from shared.checkpoint import replace_atomically, seal

Metric = Literal["l1", "l2", "inf"]

METRICS: tuple[Metric, ...] = ("l1", "l2", "inf")
_CDIST_NAME: dict[str, str] = {"l1": "cityblock", "l2": "euclidean", "inf": "chebyshev"}

FORMAT = "lsr-roadmap"
FORMAT_VERSION = 1
JSON_NAME = "roadmap.json"
ARRAYS_NAME = "roadmap.safetensors"
_ARRAY_KEYS = ("nodes", "node_sizes", "edges", "edge_weights", "point_node")

# Relative slack added to every bound used to skip work (triangle inequality, projections).
# Float64 distances and projections of latents are off by about 1e-14 relative, far less, so the
# bounds stay conservative. Bounds only ever decide what to skip, never what to join.
_ROUNDING = 1e-9
_SLACK = 1.0 + _ROUNDING
# Phase 2 first covers the points with coarse balls of this many epsilons (see connected_regions).
_COARSE_RADIUS = 2.0
# Points sampled per round to pick the coarse centres.
_COARSE_SAMPLE = 4096
# Entries per temporary distance block: bounds memory at about 32 MB per block.
_BLOCK = 1 << 22
# Directions tried to separate two stars before comparing their members pair by pair.
_DIRECTIONS = 4
# Entries per block when looking for a single close pair: small, to stop early.
_SEARCH_BLOCK = 1 << 16


class RoadmapError(ValueError):
    """Bad input to the builder, or a roadmap folder that is missing or malformed."""


def metric_p(metric: Metric) -> float:
    """The Minkowski p of a metric, as scipy's cKDTree wants it."""
    _check_metric(metric)
    return {"l1": 1.0, "l2": 2.0, "inf": math.inf}[metric]


def _check_metric(metric: str) -> None:
    if metric not in METRICS:
        raise RoadmapError(f"metric must be one of {list(METRICS)}, got {metric!r}")


def pair_distances(z1: np.ndarray, z2: np.ndarray, metric: Metric) -> np.ndarray:
    """Distances (float64) between rows of z1 and z2, broadcast like z1 - z2 over leading axes.

    Works in blocks of rows, so large inputs never need a second full-size temporary.
    """
    _check_metric(metric)
    try:
        a, b = np.broadcast_arrays(np.asarray(z1, np.float64), np.asarray(z2, np.float64))
    except ValueError:
        raise RoadmapError(
            f"pair_distances needs shapes that broadcast, got {np.shape(z1)} and {np.shape(z2)}"
        ) from None
    if a.ndim == 0:
        raise RoadmapError("pair_distances needs vectors, got scalars")
    a2 = a.reshape(-1, a.shape[-1])
    b2 = b.reshape(-1, b.shape[-1])
    out = np.empty(len(a2), dtype=np.float64)
    step = max(1, _BLOCK // max(1, a2.shape[1]))
    for s in range(0, len(a2), step):
        out[s : s + step] = _rows(a2[s : s + step], b2[s : s + step], metric)
    return out.reshape(a.shape[:-1])


def _rows(a: np.ndarray, b: np.ndarray, metric: str) -> np.ndarray:
    diff = np.abs(a - b)
    if metric == "l1":
        return diff.sum(axis=1)
    if metric == "l2":
        return np.sqrt(np.einsum("ij,ij->i", diff, diff))
    return diff.max(axis=1, initial=0.0)


def _distances_to(
    x: np.ndarray, rows: np.ndarray, targets: np.ndarray, which: np.ndarray, metric: str
) -> np.ndarray:
    """Distance from x[rows[i]] to targets[which[i]] for every i, without an N x D copy."""
    out = np.empty(len(rows), dtype=np.float64)
    step = max(1, _BLOCK // x.shape[1])
    for s in range(0, len(rows), step):
        out[s : s + step] = _rows(x[rows[s : s + step]], targets[which[s : s + step]], metric)
    return out


@dataclass(frozen=True)
class RoadmapConfig:
    """How to build a roadmap: the metric d, epsilon's weight w, and the pruning threshold."""

    metric: Metric = "l1"
    w_eps: float = 1.0
    min_samples: int = 3  # prune regions with fewer members than this, then isolated nodes

    def __post_init__(self) -> None:
        _check_metric(self.metric)
        if isinstance(self.w_eps, bool) or not isinstance(self.w_eps, int | float):
            raise RoadmapError(f"w_eps must be a number, got {self.w_eps!r}")
        if not math.isfinite(self.w_eps):
            raise RoadmapError(f"w_eps must be finite, got {self.w_eps!r}")
        if isinstance(self.min_samples, bool) or not isinstance(self.min_samples, int):
            raise RoadmapError(f"min_samples must be an integer, got {self.min_samples!r}")
        if self.min_samples < 1:
            raise RoadmapError(f"min_samples must be >= 1, got {self.min_samples}")


# --------------------------------------------------------------------------------------------
# Phase 2: connected components of the epsilon-graph
# --------------------------------------------------------------------------------------------


class _UnionFind:
    """Disjoint sets over 0..n-1; the smaller id becomes the root, so results are deterministic."""

    def __init__(self) -> None:
        self.parent: list[int] = []

    def add(self) -> int:
        self.parent.append(len(self.parent))
        return len(self.parent) - 1

    def find(self, i: int) -> int:
        parent = self.parent
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    def union(self, i: int, j: int) -> bool:
        ri, rj = self.find(i), self.find(j)
        if ri == rj:
            return False
        self.parent[max(ri, rj)] = min(ri, rj)
        return True


def _greedy_cover(
    x: np.ndarray, radius: float, metric: str, links: bool
) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int]]]:
    """Leaders in index order: every point joins the first leader closer than `radius` (strict).

    Returns the leaders' row numbers, each row's leader number and, when `links`, the pairs
    (earlier leader number, new leader number) for every earlier group that has a member closer
    than `radius` to a new leader: such groups are adjacent in the radius-graph.
    """
    n = len(x)
    owner = np.full(n, -1, dtype=np.int64)
    leaders: list[int] = []
    found: list[tuple[int, int]] = []
    name = _CDIST_NAME[metric]
    for i in range(n):
        if owner[i] >= 0:
            continue
        g = len(leaders)
        leaders.append(i)
        # Every row before i is owned already; only rows that are still free can join.
        rows = np.arange(n) if links else i + np.flatnonzero(owner[i:] < 0)
        near = rows[cdist(x[i : i + 1], x[rows], name)[0] < radius]
        owned = owner[near]
        if links:
            found.extend((int(h), g) for h in np.unique(owned[owned >= 0]))
        owner[near[owned < 0]] = g
    return np.asarray(leaders, dtype=np.int64), owner, found


def _nearest_centre(x32: np.ndarray, rows: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """For each of x32[rows], the index of the nearest centre in L2 (one matrix product a block).

    Only a guess at a good centre, in float32 for speed: callers measure the true distance.
    """
    c32 = centres.astype(np.float32)
    half_sq = 0.5 * np.einsum("ij,ij->i", c32, c32)
    out = np.empty(len(rows), dtype=np.int64)
    step = max(1, _BLOCK // max(1, len(centres)))
    for s in range(0, len(rows), step):
        score = x32[rows[s : s + step]] @ c32.T  # argmax of x.c - |c|^2 / 2 = nearest centre
        score -= half_sq
        out[s : s + step] = np.argmax(score, axis=1)
    return out


def _coarse_cover(x: np.ndarray, radius: float, metric: Metric) -> np.ndarray:
    """Split the points into balls of the given radius around centres that are data points.

    Each round greedily picks centres among a sample of the uncovered points, then hands every
    uncovered point to its nearest new centre if that centre is closer than `radius`. A class of
    the data costs one centre, not one pass over all points per centre.
    """
    n = len(x)
    x32 = x.astype(np.float32)
    owner = np.full(n, -1, dtype=np.int64)
    remaining = np.random.default_rng(0).permutation(n)
    n_centres = 0
    while remaining.size:
        sample = remaining[:_COARSE_SAMPLE]
        local, _, _ = _greedy_cover(x[sample], radius, metric, links=False)
        centres = x[sample[local]]
        near = _nearest_centre(x32, remaining, centres)
        near[local] = np.arange(len(local))  # a centre always covers itself: the loop ends
        dist = _distances_to(x, remaining, centres, near, metric)
        covered = dist < radius
        owner[remaining[covered]] = n_centres + near[covered]
        n_centres += len(local)
        remaining = remaining[~covered]
    return owner


def _groups(labels: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Members of each label as (order, bounds): label k owns order[bounds[k]:bounds[k + 1]]."""
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(count + 1))
    return order, bounds


def _canonical(labels: np.ndarray) -> np.ndarray:
    """Renumber labels 0.. by the smallest point index they hold."""
    _, first, inverse = np.unique(labels, return_index=True, return_inverse=True)
    rank = np.empty(len(first), dtype=np.int64)
    rank[np.argsort(first, kind="stable")] = np.arange(len(first))
    return rank[inverse.ravel()]


def _dual_direction(v: np.ndarray, metric: str) -> np.ndarray:
    """A direction w with |w . u| <= ||u|| for every u and w . v = ||v|| (a norm subgradient).

    Projecting on w shrinks no distance below its projected gap, and keeps the gap between two
    leaders whole: points of two stars that lie far apart along w cannot be neighbours.
    """
    if metric == "l1":
        return np.sign(v)
    if metric == "l2":
        norm = float(np.sqrt(v @ v))
        return v / norm if norm > 0 else np.zeros_like(v)
    w = np.zeros_like(v)
    k = int(np.argmax(np.abs(v)))
    w[k] = 1.0 if v[k] >= 0 else -1.0
    return w


def _window(pa: np.ndarray, pb: np.ndarray, half: float) -> tuple[np.ndarray, np.ndarray]:
    """Masks of the values in pa (and pb) that have a value of the other within +-half."""
    if pa.max() < pb.min() - half or pa.min() > pb.max() + half:
        return np.zeros(len(pa), dtype=bool), np.zeros(len(pb), dtype=bool)
    pb_sorted = np.sort(pb)
    pa_sorted = np.sort(pa)
    keep_a = np.searchsorted(pb_sorted, pa + half, "right") > np.searchsorted(
        pb_sorted, pa - half, "left"
    )
    keep_b = np.searchsorted(pa_sorted, pb + half, "right") > np.searchsorted(
        pa_sorted, pb - half, "left"
    )
    return keep_a, keep_b


def _touch(
    xa: np.ndarray,
    xb: np.ndarray,
    direction: np.ndarray,
    slack: float,
    eps: float,
    metric: str,
) -> bool:
    """Whether some row of xa is closer than eps to some row of xb.

    Projections on a direction w that shrinks no distance (see _dual_direction) differ by no
    more than the distance itself, so rows whose projections lie eps or more from every
    projection of the other set cannot have a neighbour there. The first direction runs between
    the two stars' leaders, which settles most pairs of stars from different classes without
    comparing any rows; the next ones run between the means of the rows left. `slack` covers
    the rounding of the projections.
    """
    half = eps * _SLACK + slack
    for _ in range(_DIRECTIONS):
        w = _dual_direction(direction, metric)
        keep_a, keep_b = _window(xa @ w, xb @ w, half)
        if not keep_a.any():
            return False
        if keep_a.all() and keep_b.all():
            break
        xa = xa[keep_a]
        xb = xb[keep_b]
        direction = xb.mean(axis=0) - xa.mean(axis=0)
    name = _CDIST_NAME[metric]
    step = max(1, _SEARCH_BLOCK // len(xb))
    return any(
        bool((cdist(xa[s : s + step], xb, name) < eps).any()) for s in range(0, len(xa), step)
    )


def connected_regions(
    points: np.ndarray, eps: float, metric: Metric
) -> tuple[np.ndarray, dict[str, Any]]:
    """Connected components of the graph joining points closer than eps (strict '<').

    Returns a label per point, numbered 0.. by the smallest point index in each component, and
    counters. Comparing all pairs is O(N^2), and KD-trees stop pruning in 64 dimensions, so:

    1. Coarse balls of radius 2 eps around sampled centres split the points roughly by class
       (see _coarse_cover); they only bound the work of step 2.
    2. Inside each coarse ball, greedy "stars" in index order: a leader and every free point
       closer than eps to it. A star is connected (each member touches its leader), and a star
       whose leader is closer than eps to a member of an earlier star is united with it.
    3. Two stars can only touch if their leaders are closer than both radii plus eps (triangle
       inequality). For each such pair not yet united, look for one member pair closer than
       eps, after dropping the members that projections prove too far away (see _touch).

    Every union rests on a distance measured below eps, and every pair skipped is eps or more
    apart by the triangle inequality or a projection, with a slack far above rounding: the
    partition is the brute-force one (up to how the last bit of a distance rounds). Clustered
    data costs about one pass per coarse ball and per star over its neighbourhood; points
    without clusters in many dimensions (each its own ball) degrade toward O(N^2).
    """
    _check_metric(metric)
    x = np.ascontiguousarray(points, dtype=np.float64)
    if x.ndim != 2:
        raise RoadmapError(f"points must have shape (N, D), got {x.shape}")
    if not np.isfinite(x).all():
        raise RoadmapError("points must be finite (no NaN or inf)")
    n = len(x)
    info: dict[str, Any] = {
        "coarse_balls": 0,
        "stars": 0,
        "star_pairs": 0,
        "star_checks": 0,
        "star_joins": 0,
    }
    if n == 0:
        return np.zeros(0, dtype=np.int64), info
    if not eps > 0:  # no distance is below eps: every point is its own region
        return np.arange(n, dtype=np.int64), info

    # 1. Coarse balls.
    t0 = time.perf_counter()
    coarse = _coarse_cover(x, _COARSE_RADIUS * eps, metric)
    n_coarse = int(coarse.max()) + 1
    info["coarse_balls"] = n_coarse
    t1 = time.perf_counter()

    # 2. Stars inside each coarse ball (members in index order: deterministic).
    star = np.empty(n, dtype=np.int64)
    star_leader: list[np.ndarray] = []
    sets = _UnionFind()
    order, bounds = _groups(coarse, n_coarse)
    for c in range(n_coarse):
        members = order[bounds[c] : bounds[c + 1]]
        leaders, owner, links = _greedy_cover(x[members], eps, metric, links=True)
        base = len(sets.parent)
        for _ in leaders:
            sets.add()
        for i, j in links:
            sets.union(base + i, base + j)
        star[members] = base + owner
        star_leader.append(members[leaders])
    leader = np.concatenate(star_leader)
    n_stars = len(leader)
    info["stars"] = n_stars
    t2 = time.perf_counter()

    # 3. Pairs of stars that may touch.
    s_order, s_bounds = _groups(star, n_stars)
    xs = x[s_order]  # star k owns the rows s_bounds[k]:s_bounds[k + 1]
    lx = x[leader]
    to_leader = _distances_to(xs, np.arange(n), lx, star[s_order], metric)
    radius = np.maximum.reduceat(to_leader, s_bounds[:-1])  # no star is empty
    pairs = cKDTree(lx).query_pairs(
        (eps + 2.0 * radius.max()) * _SLACK, p=metric_p(metric), output_type="ndarray"
    )
    if len(pairs):
        gap = pair_distances(lx[pairs[:, 0]], lx[pairs[:, 1]], metric)
        keep = gap <= (radius[pairs[:, 0]] + radius[pairs[:, 1]] + eps) * _SLACK
        pairs = pairs[keep][np.argsort(gap[keep], kind="stable")]  # likely joins first
    info["star_pairs"] = len(pairs)
    t3 = time.perf_counter()
    # A projection on w (|w_i| <= 1) rounds by far less than 1e-9 of the row's L1 norm.
    norm1 = np.maximum.reduceat(np.abs(xs).sum(axis=1), s_bounds[:-1])
    checks = joins = 0
    for a, b in pairs.tolist():
        if sets.find(a) == sets.find(b):
            continue
        checks += 1
        if _touch(
            xs[s_bounds[a] : s_bounds[a + 1]],
            xs[s_bounds[b] : s_bounds[b + 1]],
            lx[b] - lx[a],
            _ROUNDING * (norm1[a] + norm1[b]),
            eps,
            metric,
        ):
            sets.union(a, b)
            joins += 1
    info["star_checks"] = checks
    info["star_joins"] = joins
    t4 = time.perf_counter()
    info["seconds"] = {
        "coarse": t1 - t0,
        "stars": t2 - t1,
        "star_pairs": t3 - t2,
        "star_checks": t4 - t3,
    }

    roots = np.fromiter((sets.find(i) for i in range(n_stars)), dtype=np.int64, count=n_stars)
    return _canonical(roots[star]), info


# --------------------------------------------------------------------------------------------
# Building the roadmap
# --------------------------------------------------------------------------------------------


def _check_inputs(
    z1: np.ndarray, z2: np.ndarray, a: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    z1 = np.asarray(z1)
    z2 = np.asarray(z2)
    a = np.asarray(a)
    if z1.ndim != 2 or z1.shape != z2.shape:
        raise RoadmapError(f"z1 and z2 must both have shape (N, D), got {z1.shape} and {z2.shape}")
    if a.shape != (len(z1),):
        raise RoadmapError(f"a must have shape ({len(z1)},), got {a.shape}")
    if not (np.issubdtype(z1.dtype, np.number) and np.issubdtype(z2.dtype, np.number)):
        raise RoadmapError(f"z1 and z2 must be numeric, got {z1.dtype} and {z2.dtype}")
    if not (np.isfinite(z1).all() and np.isfinite(z2).all()):
        raise RoadmapError("z1 and z2 must be finite (no NaN or inf)")
    if not np.isin(a, (0, 1)).all():
        raise RoadmapError("a must hold only 0 (no-action pair) and 1 (action pair)")
    if len(z1) == 0 or z1.shape[1] == 0:
        raise RoadmapError(f"need at least one pair of non-empty latents, got shape {z1.shape}")
    return z1, z2, a.astype(bool)


def build_roadmap(
    z1: np.ndarray, z2: np.ndarray, a: np.ndarray, config: RoadmapConfig | None = None
) -> Roadmap:
    """Build the LSR from encoded training tuples (z1[i], z2[i], a[i]) (paper Algorithm 1)."""
    config = config or RoadmapConfig()
    metric = config.metric
    start = time.perf_counter()
    z1, z2, act = _check_inputs(z1, z2, a)
    n, dim = z1.shape

    # Phase 1: the reference graph. Its vertices are all 2N latents, numbered z1[0], z2[0],
    # z1[1], ...; its edges are the action pairs (2i, 2i + 1).
    points = np.empty((2 * n, dim), dtype=np.float64)
    points[0::2] = z1
    points[1::2] = z2
    pair_ids = np.flatnonzero(act)
    t_phase1 = time.perf_counter()

    # epsilon = mu0 + w * sigma0 over the no-action pairs' distances (population std).
    still = np.flatnonzero(~act)
    if not len(still):
        raise RoadmapError("epsilon needs no-action pairs (a == 0), and there are none")
    d0 = pair_distances(points[2 * still], points[2 * still + 1], metric)
    mu0 = float(d0.mean())
    sigma0 = float(d0.std())
    epsilon = mu0 + config.w_eps * sigma0
    t_eps = time.perf_counter()

    # Phase 2: the valid regions.
    labels, phase2 = connected_regions(points, epsilon, metric)
    n_regions = int(labels.max()) + 1
    t_phase2 = time.perf_counter()

    # Phase 3: a node per region (the member closest to the region mean) and an edge per pair
    # of regions joined by action pairs, weighted by how many (each pair counted once).
    sizes = np.bincount(labels, minlength=n_regions)
    sums = (
        sparse.csr_matrix((np.ones(2 * n), (labels, np.arange(2 * n))), shape=(n_regions, 2 * n))
        @ points
    )
    means = sums / sizes[:, None]
    to_mean = _distances_to(points, np.arange(2 * n), means, labels, metric)
    first = np.concatenate(([0], np.cumsum(sizes)[:-1]))
    representative = np.lexsort((to_mean, labels))[first]  # ties: the smallest point index

    r1 = labels[2 * pair_ids]
    r2 = labels[2 * pair_ids + 1]
    across = r1 != r2
    lo = np.minimum(r1, r2)[across]
    hi = np.maximum(r1, r2)[across]
    keys, weights = np.unique(lo * n_regions + hi, return_counts=True)
    edges = np.stack([keys // n_regions, keys % n_regions], axis=1).astype(np.int64)
    t_phase3 = time.perf_counter()

    # Pruning: regions with fewer than min_samples members, then nodes left without an edge.
    big = sizes >= config.min_samples
    kept_edge = big[edges[:, 0]] & big[edges[:, 1]]
    linked = np.zeros(n_regions, dtype=bool)
    linked[edges[kept_edge].ravel()] = True
    kept = big & linked
    new_id = np.full(n_regions, -1, dtype=np.int64)
    new_id[kept] = np.arange(int(kept.sum()))
    final_edges = new_id[edges[kept_edge]].reshape(-1, 2)  # renumbering keeps the order
    final_weights = weights[kept_edge].astype(np.int64)
    point_node = new_id[labels]
    t_prune = time.perf_counter()

    stats: dict[str, Any] = {
        "points": 2 * n,
        "action_pairs": len(pair_ids),
        "no_action_pairs": len(still),
        "regions_before_pruning": n_regions,
        "edges_before_pruning": len(edges),
        "edge_weight_before_pruning": int(weights.sum()),
        "action_pairs_inside_one_region": int((~across).sum()),
        "regions_too_small": int((~big).sum()),
        "regions_isolated": int((big & ~linked).sum()),
        "nodes": int(kept.sum()),
        "edges": len(final_edges),
        "edge_weight": int(final_weights.sum()),
        "points_without_node": int((point_node < 0).sum()),
        "phase2": phase2,
        "seconds": {
            "phase1": t_phase1 - start,
            "epsilon": t_eps - t_phase1,
            "phase2": t_phase2 - t_eps,
            "phase3": t_phase3 - t_phase2,
            "pruning": t_prune - t_phase3,
            "total": t_prune - start,
        },
    }
    return Roadmap(
        config=config,
        epsilon=epsilon,
        mu0=mu0,
        sigma0=sigma0,
        nodes=points[representative[kept]].astype(np.float32),
        node_sizes=sizes[kept].astype(np.int64),
        edges=final_edges,
        edge_weights=final_weights,
        point_node=point_node,
        stats=stats,
    )


# --------------------------------------------------------------------------------------------
# The roadmap
# --------------------------------------------------------------------------------------------


@dataclass(eq=False)
class Roadmap:
    """A built LSR: one node per kept region, undirected edges, and what each latent became."""

    config: RoadmapConfig
    epsilon: float
    mu0: float
    sigma0: float
    nodes: np.ndarray  # (K, D) float32: each node's representative latent
    node_sizes: np.ndarray  # (K,) int64: members per node
    edges: np.ndarray  # (E, 2) int64, i < j, sorted
    edge_weights: np.ndarray  # (E,) int64: supporting action pairs, each counted once
    point_node: np.ndarray  # (2N,) int64: node of z1[0], z2[0], z1[1], ...; -1 when pruned
    stats: dict[str, Any] = field(default_factory=dict)
    _tree: cKDTree | None = field(default=None, init=False, repr=False)
    _adjacency: tuple[np.ndarray, np.ndarray] | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        self._validate()

    def _validate(self) -> None:
        """Raise RoadmapError naming the first field that is not a consistent roadmap."""
        if not isinstance(self.config, RoadmapConfig):
            raise RoadmapError(f"config must be a RoadmapConfig, got {type(self.config).__name__}")
        for name in ("epsilon", "mu0", "sigma0"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise RoadmapError(f"{name} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise RoadmapError(f"{name} must be finite, got {value!r}")
        if not isinstance(self.stats, dict):
            raise RoadmapError(f"stats must be a dict, got {type(self.stats).__name__}")
        _expect(self.nodes, "nodes", 2, np.float32)
        k = len(self.nodes)
        _expect(self.node_sizes, "node_sizes", 1, np.int64, (k,))
        _expect(self.edges, "edges", 2, np.int64)
        if self.edges.shape[1] != 2:
            raise RoadmapError(f"edges must have shape (E, 2), got {self.edges.shape}")
        _expect(self.edge_weights, "edge_weights", 1, np.int64, (len(self.edges),))
        _expect(self.point_node, "point_node", 1, np.int64)
        if not np.isfinite(self.nodes).all():
            raise RoadmapError("nodes must be finite")
        if (self.node_sizes < 1).any():
            raise RoadmapError("node_sizes must be >= 1")
        if len(self.edges):
            i, j = self.edges[:, 0], self.edges[:, 1]
            if (i < 0).any() or (j >= k).any() or (i >= j).any():
                raise RoadmapError(f"edges must be pairs i < j of node ids in 0..{k - 1}")
            key = i * k + j
            if (np.diff(key) <= 0).any():
                raise RoadmapError("edges must be sorted and unique")
        if (self.edge_weights < 1).any():
            raise RoadmapError("edge_weights must be >= 1")
        if len(self.point_node) and ((self.point_node < -1).any() or (self.point_node >= k).any()):
            raise RoadmapError(f"point_node must hold -1 or node ids in 0..{k - 1}")

    @property
    def num_nodes(self) -> int:
        return len(self.nodes)

    def nearest_node(self, z: np.ndarray) -> np.ndarray | int:
        """The node closest in the roadmap's metric to a latent (D,) or to each of (M, D)."""
        q = np.asarray(z, dtype=np.float64)
        dim = self.nodes.shape[1]
        if q.ndim not in (1, 2) or q.shape[-1] != dim:
            raise RoadmapError(f"z must have shape ({dim},) or (M, {dim}), got {q.shape}")
        if not np.isfinite(q).all():
            raise RoadmapError("z must be finite")
        if not self.num_nodes:
            raise RoadmapError("the roadmap has no nodes")
        if self._tree is None:
            self._tree = cKDTree(self.nodes.astype(np.float64))
        _, idx = self._tree.query(q, k=1, p=metric_p(self.config.metric))
        return int(idx) if q.ndim == 1 else np.asarray(idx, dtype=np.int64)

    def _neighbour_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """CSR adjacency (indptr, indices), neighbours sorted ascending, built once."""
        if self._adjacency is None:
            rows = np.concatenate([self.edges[:, 0], self.edges[:, 1]])
            cols = np.concatenate([self.edges[:, 1], self.edges[:, 0]])
            order = np.lexsort((cols, rows))
            indptr = np.searchsorted(rows[order], np.arange(self.num_nodes + 1))
            self._adjacency = (indptr, cols[order])
        return self._adjacency

    def _node_id(self, node: int, name: str) -> int:
        try:
            i = operator.index(node)
        except TypeError:
            raise RoadmapError(f"{name} must be an integer node id, got {node!r}") from None
        if not 0 <= i < self.num_nodes:
            raise RoadmapError(f"{name} must be a node id in 0..{self.num_nodes - 1}, got {i}")
        return i

    def neighbours(self, node: int) -> list[int]:
        """Nodes sharing an edge with `node`, ascending."""
        i = self._node_id(node, "node")
        indptr, indices = self._neighbour_arrays()
        return indices[indptr[i] : indptr[i + 1]].tolist()

    def shortest_paths(self, src: int, dst: int, max_paths: int = 16) -> list[list[int]]:
        """All shortest paths by hop count from src to dst, at most max_paths of them.

        Paths come in lexicographic order of their node ids, so the same roadmap always gives
        the same plans. [] when dst cannot be reached; [[src]] when src == dst.
        """
        s = self._node_id(src, "src")
        t = self._node_id(dst, "dst")
        if isinstance(max_paths, bool) or not isinstance(max_paths, int) or max_paths < 1:
            raise RoadmapError(f"max_paths must be an integer >= 1, got {max_paths!r}")
        if s == t:
            return [[s]]
        indptr, indices = self._neighbour_arrays()
        graph = sparse.csr_matrix(
            (np.ones(len(indices)), indices, indptr), shape=(self.num_nodes, self.num_nodes)
        )
        hops = shortest_path(graph, directed=True, unweighted=True, indices=[s, t])
        from_s, to_t = hops[0], hops[1]
        if not math.isfinite(from_s[t]):
            return []

        def onward(u: int) -> list[int]:
            # Neighbours one hop further from src and one hop closer to dst: on a shortest path.
            nbrs = indices[indptr[u] : indptr[u + 1]]
            ok = (from_s[nbrs] == from_s[u] + 1) & (to_t[nbrs] == to_t[u] - 1)
            return nbrs[ok].tolist()

        paths: list[list[int]] = []
        path = [s]
        stack = [iter(onward(s))]
        while stack:  # depth-first, smallest ids first: lexicographic order
            v = next(stack[-1], None)
            if v is None:
                stack.pop()
                path.pop()
            elif v == t:
                paths.append([*path, v])
                if len(paths) == max_paths:
                    break
            else:
                path.append(v)
                stack.append(iter(onward(v)))
        return paths

    def save(self, directory: str | Path) -> None:
        """Write roadmap.safetensors (arrays) and roadmap.json (config, scalars, stats)."""
        out = Path(directory)
        out.mkdir(parents=True, exist_ok=True)
        arrays = {key: np.ascontiguousarray(getattr(self, key)) for key in _ARRAY_KEYS}
        replace_atomically(out / ARRAYS_NAME, lambda tmp: save_file(arrays, str(tmp)))
        meta = {
            "format": FORMAT,
            "version": FORMAT_VERSION,
            "config": asdict(self.config),
            "epsilon": self.epsilon,
            "mu0": self.mu0,
            "sigma0": self.sigma0,
            "stats": self.stats,
        }
        text = json.dumps(meta, indent=2, allow_nan=False) + "\n"
        replace_atomically(out / JSON_NAME, lambda tmp: tmp.write_text(text))
        seal(out, [ARRAYS_NAME, JSON_NAME])  # labels.json (build's, after this) is not served

    @classmethod
    def load(cls, directory: str | Path) -> Roadmap:
        """Read a folder written by save; RoadmapError names what is missing or malformed."""
        folder = Path(directory)
        if not folder.is_dir():
            raise RoadmapError(f"{folder}: no such roadmap folder")
        meta_path = folder / JSON_NAME
        arrays_path = folder / ARRAYS_NAME
        for path in (meta_path, arrays_path):
            if not path.is_file():
                raise RoadmapError(f"{path}: missing")
        try:
            meta = json.loads(meta_path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise RoadmapError(f"{meta_path}: not readable JSON ({exc})") from exc
        if not isinstance(meta, dict):
            raise RoadmapError(f"{meta_path}: expected a JSON object")
        if meta.get("format") != FORMAT or meta.get("version") != FORMAT_VERSION:
            raise RoadmapError(
                f"{meta_path}: expected format {FORMAT!r} version {FORMAT_VERSION}, got "
                f"{meta.get('format')!r} version {meta.get('version')!r}"
            )
        missing = [k for k in ("config", "epsilon", "mu0", "sigma0", "stats") if k not in meta]
        if missing:
            raise RoadmapError(f"{meta_path}: missing {', '.join(missing)}")
        if not isinstance(meta["config"], dict):
            raise RoadmapError(f"{meta_path}: config must be an object")
        try:
            config = RoadmapConfig(**meta["config"])
        except TypeError as exc:
            raise RoadmapError(f"{meta_path}: bad config ({exc})") from exc
        except RoadmapError as exc:
            raise RoadmapError(f"{meta_path}: bad config ({exc})") from exc
        try:
            arrays = load_file(str(arrays_path))
        except Exception as exc:  # safetensors raises its own error types for corrupt files
            raise RoadmapError(f"{arrays_path}: not a readable safetensors file ({exc})") from exc
        missing = [k for k in _ARRAY_KEYS if k not in arrays]
        if missing:
            raise RoadmapError(f"{arrays_path}: missing arrays {', '.join(missing)}")
        try:
            return cls(
                config=config,
                epsilon=meta["epsilon"],
                mu0=meta["mu0"],
                sigma0=meta["sigma0"],
                stats=meta["stats"],
                **{k: arrays[k] for k in _ARRAY_KEYS},
            )
        except RoadmapError as exc:
            raise RoadmapError(f"{folder}: {exc}") from exc


def _expect(
    array: Any,
    name: str,
    ndim: int,
    dtype: type,
    shape: tuple[int, ...] | None = None,
) -> None:
    if not isinstance(array, np.ndarray):
        raise RoadmapError(f"{name} must be a numpy array, got {type(array).__name__}")
    if array.ndim != ndim or array.dtype != dtype:
        raise RoadmapError(
            f"{name} must be a {ndim}-D {np.dtype(dtype).name} array, "
            f"got {array.ndim}-D {array.dtype}"
        )
    if shape is not None and array.shape != shape:
        raise RoadmapError(f"{name} must have shape {shape}, got {array.shape}")
