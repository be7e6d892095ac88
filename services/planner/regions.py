"""Phase 2 of the Latent Space Roadmap: the valid regions, and the distances they rest on.

`connected_regions` is exactly the connected components of the epsilon-graph (single linkage cut
at epsilon, strict '<') without comparing every pair of latents; `stable_epsilon` picks the cut
from the data when no-action pairs are too few to estimate it (see its docstring).
"""

from __future__ import annotations

import math
import time
from typing import Any, Literal

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

Metric = Literal["l1", "l2", "inf"]

METRICS: tuple[Metric, ...] = ("l1", "l2", "inf")
CDIST_NAME: dict[str, str] = {"l1": "cityblock", "l2": "euclidean", "inf": "chebyshev"}

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
    name = CDIST_NAME[metric]
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
    name = CDIST_NAME[metric]
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
# Choosing epsilon from the data
# --------------------------------------------------------------------------------------------

# The scan's grid: epsilon grows by this factor a step.
_GRID_RATIO = 2.0**0.25
# A partition is stable while the region count falls by at most this fraction (or one region).
_STABLE_TOLERANCE = 0.01
# The shortest stable range accepted, as the ratio of its ends.
_STABLE_SPAN = 2.0
# A flat range with fewer regions than this share of the finest flat range's groups states.
_COARSEST = 0.5
# The scan stops once more than this share of the action pairs falls inside one region.
_MERGED_ACTIONS = 0.01
# ... or once, with this share of the no-action pairs inside one region, regions holding at least
# _WHOLE of the typical region's images (and _MIN_WHOLE) each make up half of a step's joins:
# whole states chaining. Below _MIN_WHOLE images a region says too little about its state.
_STILL_JOINED = 0.99
_WHOLE = 0.5
_MIN_WHOLE = 3


def stable_epsilon(
    points: np.ndarray, still: np.ndarray, moved: np.ndarray, metric: Metric
) -> tuple[float | None, dict[str, Any]]:
    """The geometric middle of the longest range of epsilon over which the regions stay the same.

    `points` are the latents z1[0], z2[0], z1[1], ...; `still` and `moved` the indices of the
    no-action and action pairs. Algorithm 1's epsilon = mu0 + w sigma0 sits at the scale of one
    no-action pair; it joins a state's images into one region only when there are enough of
    them to chain together, and with a handful of images per state it splits states (1000
    box-stacking tuples: 527 regions for 288 states). Scanning epsilon upward from mu0 on a
    geometric grid, the region count falls fast while states still split, stays flat while
    every region is one state, and falls again when states chain together. The scan stops
    where the regions start to swallow action pairs, whose two images show different states by
    definition, or where whole regions join each other: once the no-action pairs lie inside
    regions, a step whose joins are mostly of two regions each holding half the typical
    region's images or more is states chaining, not the last pieces of a state coming home
    (those are small, and many join in a step). Of the flat ranges below that (each at least a
    factor 2 long), the longest is taken among those with at least _COARSEST of the finest
    one's regions, and epsilon is its geometric middle: the farthest from both splitting and
    chaining. The bound on coarseness: a partition into groups of states can be flat too where
    no move stays inside a group (box stacking's 12 stack-height profiles: every move changes
    one), and with 1000 camera tuples that range was the longer (issue 47: 12 nodes for 288
    states); the pieces of split states joining at most halve the count. Where states chain
    before any range is flat (300 T-shirt tuples: two of 25 views join one step after the last
    pieces do), epsilon is the last step before the chaining: the no-action pairs joined, the
    most pieces of states joined, no two states. None when no range is found, for example in a
    latent space without structure; the caller falls back.
    """
    d_still = pair_distances(points[2 * still], points[2 * still + 1], metric)
    d_moved = pair_distances(points[2 * moved], points[2 * moved + 1], metric)
    info: dict[str, Any] = {"grid": [], "regions": []}
    lo = float(np.mean(d_still)) if len(d_still) else 0.0
    hi = float(np.quantile(d_moved, 0.01)) if len(d_moved) else lo * 2.0**10
    if not (lo > 0 and hi > lo):
        return None, info
    steps = math.floor(math.log(hi / lo) / math.log(_GRID_RATIO)) + 1
    counts: list[int] = []
    previous: np.ndarray | None = None
    for eps in lo * _GRID_RATIO ** np.arange(steps):
        labels = connected_regions(points, float(eps), metric)[0]
        merged = float(np.mean(labels[2 * moved] == labels[2 * moved + 1])) if len(moved) else 0.0
        count = int(labels.max()) + 1
        info["grid"].append(float(eps))
        info["regions"].append(count)
        if merged > _MERGED_ACTIONS or count == 1:
            info["stop"] = "action pairs inside regions"
            break
        if "joined" in info and previous is not None and _whole_regions_join(previous, labels):
            info["stop"] = "whole regions join"
            break
        joined = np.mean(labels[2 * still] == labels[2 * still + 1]) if len(still) else 0.0
        if "joined" not in info and joined >= _STILL_JOINED:
            info["joined"] = float(eps)
        counts.append(count)
        previous = labels
    grid = info["grid"]
    flat: list[tuple[int, int]] = []  # the flat ranges, finest first, none inside another
    i = 0
    while i < len(counts):
        j = i
        while j + 1 < len(counts) and _flat(counts[i], counts[j + 1]):
            j += 1
        if grid[j] / grid[i] >= _STABLE_SPAN * (1 - 1e-9):
            flat.append((i, j))
            i = j + 1
        else:
            i += 1
    if flat:
        finest = counts[flat[0][0]]
        fine = [(i, j) for i, j in flat if counts[i] >= _COARSEST * finest]
        i, j = max(fine, key=lambda r: r[1] - r[0])  # ties: the finer
        info["range"] = [grid[i], grid[j]]
    elif info.get("stop") == "whole regions join" and info["joined"] <= grid[len(counts) - 1]:
        info["range"] = [grid[len(counts) - 1]] * 2  # the last cut before states chain
    else:
        return None, info
    low, high = info["range"]
    return float(math.sqrt(low * high)), info


def _whole_regions_join(before: np.ndarray, after: np.ndarray) -> bool:
    """Whether half or more of the joins from one cut to the next are of regions that each
    hold at least _WHOLE of the typical region's images (the median over images of their
    region's size, after the step) and at least _MIN_WHOLE."""
    fall = int(before.max()) - int(after.max())
    if fall <= 0:
        return False
    typical = float(np.median(np.bincount(after)[after]))
    pieces = np.unique(after.astype(np.int64) * (int(before.max()) + 1) + before)
    region, piece = np.divmod(pieces, int(before.max()) + 1)
    whole = np.bincount(before)[piece] >= max(_MIN_WHOLE, _WHOLE * typical)
    per_region = np.bincount(region, weights=whole)
    joins = int(np.maximum(per_region - 1, 0).sum())
    return joins > 0 and joins >= 0.5 * fall


def _flat(first: int, last: int) -> bool:
    """Whether the region count went from `first` to `last` without changing the partition much."""
    return first - last <= max(1.0, _STABLE_TOLERANCE * first)
