"""The Latent Space Roadmap (LSR, paper Algorithm 1): build it, query it, save and load it.

Phase 1 numbers the latents z1[0], z2[0], z1[1], z2[1], ... and keeps the action pairs as the
reference edges. Phase 2 groups the latents into valid regions: the connected components of the
graph joining two latents whose distance is strictly below epsilon. Phase 3 makes one node per
region (the member closest to the region mean) and one edge per pair of regions that an action
pair joins, weighted by the number of such action pairs. Small regions and then isolated nodes
are pruned.

Phase 2 is exact (the same partition as comparing every pair of latents) but never compares every
pair; see `services.planner.regions`. Epsilon and the pruning threshold follow the data by default
(`eps_rule="stable"`, `min_samples=None`), which keeps the roadmap whole with a few images per
state; `eps_rule="paper"` with `min_samples=3` is Algorithm 1 as written.
"""

from __future__ import annotations

import json
import math
import operator
import time
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from safetensors.numpy import load_file, save_file
from scipy import sparse
from scipy.sparse.csgraph import shortest_path
from scipy.spatial import cKDTree

from services.planner.exits import Turns, forbidden_turns, memory_paths
from services.planner.regions import (
    Metric,
    RoadmapError,
    _check_metric,
    _distances_to,
    connected_regions,
    metric_p,
    pair_distances,
    stable_epsilon,
)
from shared.checkpoint import replace_atomically, seal
from shared.graphs import node_components, twin_groups, walks

__all__ = [
    "Metric",
    "Roadmap",
    "RoadmapConfig",
    "RoadmapError",
    "build_roadmap",
    "connected_regions",
    "metric_p",
    "pair_distances",
]

EpsilonRule = Literal["stable", "paper"]
EPSILON_RULES: tuple[EpsilonRule, ...] = ("stable", "paper")
Matching = Literal["whitened", "metric"]
MATCHINGS: tuple[Matching, ...] = ("whitened", "metric")
# Whitened matching needs this many residual degrees of freedom (images less nodes) per latent
# dimension to estimate the within-node covariance, and shrinks it towards its mean variance by
# this share so that a dimension the images barely use is not blown up.
WHITEN_MIN_PER_DIM = 4
WHITEN_SHRINK = 0.01
# The automatic pruning threshold: this fraction of the typical point's region size.
_MIN_SAMPLES_FRACTION = 0.1

FORMAT = "lsr-roadmap"
FORMAT_VERSION = 1
JSON_NAME = "roadmap.json"
ARRAYS_NAME = "roadmap.safetensors"
_ARRAY_KEYS = ("nodes", "node_sizes", "edges", "edge_weights", "point_node")
_OPTIONAL_KEYS = ("twins", "whitening", "exits")


# config values roadmap.json leaves out: readers from before these keys know none of them
_UNSAID_DEFAULTS = (
    ("matching", "metric"),
    ("min_edge_weight", 1),
    ("one_way", False),
    ("keep_rare", True),
)


@dataclass(frozen=True)
class RoadmapConfig:
    """How to build a roadmap: the metric d, how epsilon is chosen, and the pruning threshold.

    eps_rule "paper" is Algorithm 1's epsilon = mu0 + w_eps sigma0 over the no-action distances;
    "stable" scans for the cut that keeps the regions unchanged longest (see stable_epsilon) and
    falls back to the paper's rule where no such cut exists. min_samples None prunes regions
    smaller than a tenth of the typical point's region (at least 1): 3 with the shipped box
    stacking data (35 images a state), 1 with 1000 tuples (7 a state); given each tuple's
    action class and keep_rare, it keeps the small regions whose moves no big region shows
    (`_fragments`). A task whose one state takes looks that move differently (rope-box's
    bunched ropes) declares keep_rare False: there such regions are looks, not states.

    matching "whitened" matches an image to the nearest node after whitening the latents by
    the spread of images within their nodes (see fit_whitening); "metric" in d, as the paper.

    min_edge_weight drops edges fewer action pairs support (1, the paper's, keeps every one):
    an edge one or two stray images make joins states no move joins.

    one_way (set where the task declares no undo, TaskSpec.undo): an edge is known only the
    way its action pairs went, so paths take it the other way only where nothing else reaches
    the goal; the APN has never seen the action of that direction.
    """

    metric: Metric = "l1"
    w_eps: float = 1.0
    min_samples: int | None = None  # prune regions with fewer members, then isolated nodes
    eps_rule: EpsilonRule = "stable"
    matching: Matching = "whitened"
    min_edge_weight: int = 1
    one_way: bool = False
    keep_rare: bool = True

    def __post_init__(self) -> None:
        _check_metric(self.metric)
        if self.matching not in MATCHINGS:
            raise RoadmapError(f"matching must be one of {list(MATCHINGS)}, got {self.matching!r}")
        if self.eps_rule not in EPSILON_RULES:
            raise RoadmapError(
                f"eps_rule must be one of {list(EPSILON_RULES)}, got {self.eps_rule!r}"
            )
        if isinstance(self.w_eps, bool) or not isinstance(self.w_eps, int | float):
            raise RoadmapError(f"w_eps must be a number, got {self.w_eps!r}")
        if not math.isfinite(self.w_eps):
            raise RoadmapError(f"w_eps must be finite, got {self.w_eps!r}")
        weight = self.min_edge_weight
        if isinstance(weight, bool) or not isinstance(weight, int) or weight < 1:
            raise RoadmapError(f"min_edge_weight must be an integer >= 1, got {weight!r}")
        for name in ("one_way", "keep_rare"):
            if not isinstance(getattr(self, name), bool):
                raise RoadmapError(f"{name} must be true or false, got {getattr(self, name)!r}")
        if self.min_samples is None:
            return
        if isinstance(self.min_samples, bool) or not isinstance(self.min_samples, int):
            raise RoadmapError(f"min_samples must be an integer or None, got {self.min_samples!r}")
        if self.min_samples < 1:
            raise RoadmapError(f"min_samples must be >= 1, got {self.min_samples}")


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


def choose_epsilon(
    points: np.ndarray, act: np.ndarray, config: RoadmapConfig
) -> tuple[float, float, float, str, dict[str, Any]]:
    """(epsilon, mu0, sigma0, the rule that chose it, the stable rule's scan) for latents in
    the roadmap's point order and the action flags of their tuples."""
    # epsilon = mu0 + w * sigma0 over the no-action pairs' distances (population std).
    still = np.flatnonzero(~act)
    if not len(still):
        raise RoadmapError("epsilon needs no-action pairs (a == 0), and there are none")
    d0 = pair_distances(points[2 * still], points[2 * still + 1], config.metric)
    mu0 = float(d0.mean())
    sigma0 = float(d0.std())
    epsilon = mu0 + config.w_eps * sigma0
    if config.eps_rule == "stable":
        stable, scan = stable_epsilon(points, still, np.flatnonzero(act), config.metric)
        if stable is not None:
            return stable, mu0, sigma0, "stable", scan
        return epsilon, mu0, sigma0, "paper", scan
    return epsilon, mu0, sigma0, "paper", {}


def _fragments(
    labels: np.ndarray, pair_ids: np.ndarray, classes: np.ndarray, big: np.ndarray
) -> np.ndarray:
    """The small regions the default pruning drops: those a big region shows one of the moves
    of (the same action class to or from the same region: a fragment of that region's state,
    as an action leads into a state from one state only) and those no move joins to a big
    region. A small region whose moves into and out of big regions no big region shows is a
    state of its own, seen rarely, and is kept. Box stacking from 300 tuples and 2000 explored
    actions: the size rule pruned 8 states of their own (regions of 1-2 images) and kept
    Table I at 94.0; this rule keeps all 5 that a move joins (96.6). Rope-box at 2500 tuples:
    of its 196 small regions, 96 dropped (each a node's state) and 100 kept: each a node's
    state to the rules, with moves no node shows (ropes bunched otherwise)."""
    r1, r2 = labels[2 * pair_ids], labels[2 * pair_ids + 1]
    across = r1 != r2
    r1, r2, classes = r1[across], r2[across], classes[across]
    out = {(int(t), int(k)) for f, t, k in zip(r1, r2, classes, strict=True) if big[f]}
    into = {(int(f), int(k)) for f, t, k in zip(r1, r2, classes, strict=True) if big[t]}
    shown = np.zeros(len(big), dtype=bool)
    joined = np.zeros(len(big), dtype=bool)  # to or from a big region
    for f, t, k in zip(r1.tolist(), r2.tolist(), classes.tolist(), strict=True):
        shown[f] |= (t, k) in out
        shown[t] |= (f, k) in into
        joined[f] |= bool(big[t])
        joined[t] |= bool(big[f])
    return ~big & (shown | ~joined)


def fit_whitening(points: np.ndarray, point_node: np.ndarray) -> np.ndarray:
    """(D, D) W such that distances between z @ W are Mahalanobis distances under the pooled
    covariance of images within their nodes; (0, 0) where too few images share a node.

    Why: the roadmap's metric weighs every latent direction alike, but one state's images
    spread along some directions far more than two states lie apart along others. In box
    stacking at 500 tuples grown by exploration, the nearest node in L1 put 19 of 200 fresh
    images of five goal states (and 2 of 800 of random ones) in a neighbouring state's node,
    which ended closed-loop tasks one move early; whitened, 1 of 200 and 0 of 800."""
    kept = point_node >= 0
    z = np.asarray(points, np.float64)[kept]
    node = point_node[kept]
    dim = z.shape[1] if z.ndim == 2 else 0
    ids, node = np.unique(node, return_inverse=True)
    dof = len(z) - len(ids)
    if dim == 0 or dof < WHITEN_MIN_PER_DIM * dim:
        return np.zeros((0, 0), np.float32)
    sums = np.zeros((len(ids), dim))
    np.add.at(sums, node, z)
    residual = z - (sums / np.bincount(node)[:, None])[node]
    within = residual.T @ residual / dof
    mean_variance = float(np.trace(within)) / dim
    if not mean_variance > 0:  # also NaN
        return np.zeros((0, 0), np.float32)
    within = (1 - WHITEN_SHRINK) * within + WHITEN_SHRINK * mean_variance * np.eye(dim)
    values, vectors = np.linalg.eigh(within)
    whitening = (vectors / np.sqrt(values)).astype(np.float32)
    return whitening if np.isfinite(whitening).all() else np.zeros((0, 0), np.float32)


def whitening_for(config: RoadmapConfig, points: np.ndarray, point_node: np.ndarray) -> np.ndarray:
    """fit_whitening where the config matches whitened, (0, 0) where it matches in the metric."""
    if config.matching == "whitened":
        return fit_whitening(points, point_node)
    return np.zeros((0, 0), np.float32)


def build_roadmap(
    z1: np.ndarray,
    z2: np.ndarray,
    a: np.ndarray,
    config: RoadmapConfig | None = None,
    action_class: np.ndarray | None = None,
) -> Roadmap:
    """Build the LSR from encoded training tuples (z1[i], z2[i], a[i]) (paper Algorithm 1).

    `action_class` (N,), each action pair's action (`exits.action_classes`), lets the default
    pruning keep the small regions that are states of their own (see `_fragments`)."""
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
    still = np.flatnonzero(~act)
    t_phase1 = time.perf_counter()
    epsilon, mu0, sigma0, eps_rule, scan = choose_epsilon(points, act, config)
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
    min_samples = config.min_samples
    if min_samples is None:
        typical = float(np.median(sizes[labels]))  # the region size of the typical point
        min_samples = max(1, int(_MIN_SAMPLES_FRACTION * typical))
    big = sizes >= min_samples
    if config.min_samples is None and config.keep_rare and action_class is not None:
        big |= ~_fragments(labels, pair_ids, np.asarray(action_class)[pair_ids], big)
    strong = weights >= config.min_edge_weight
    kept_edge = big[edges[:, 0]] & big[edges[:, 1]] & strong
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
        "eps_rule": eps_rule,
        "epsilon_scan": scan,
        "min_samples": min_samples,
        "regions_before_pruning": n_regions,
        "edges_before_pruning": len(edges),
        "edge_weight_before_pruning": int(weights.sum()),
        "action_pairs_inside_one_region": int((~across).sum()),
        "regions_too_small": int((~big).sum()),
        "small_regions_kept": int((big & ~(sizes >= min_samples)).sum()),
        "edges_too_weak": int((~strong).sum()),
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
        whitening=whitening_for(config, points, point_node),
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
    # (T, 2) int64, i < j, sorted: nodes that no-action pairs show to be one state (growth's
    # twins); paths treat each group as one node.
    twins: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    # (D, D) float32 (fit_whitening), or (0, 0): images are matched to nodes in the metric.
    whitening: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.float32))
    # (X, 3) int64 (from node, to node, action class), sorted and unique: where the training
    # tuples' actions lead (services.planner.exits); paths take no turn these show impossible.
    exits: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int64))
    _tree: cKDTree | None = field(default=None, init=False, repr=False)
    _adjacency: tuple[np.ndarray, np.ndarray] | None = field(default=None, init=False, repr=False)
    _groups: tuple[np.ndarray, np.ndarray, np.ndarray] | None = field(
        default=None, init=False, repr=False
    )
    _component: np.ndarray | None = field(default=None, init=False, repr=False)
    _turns: Turns | None = field(default=None, init=False, repr=False)
    _unshown: list[tuple[int, int]] | None = field(default=None, init=False, repr=False)

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
        _expect(self.twins, "twins", 2, np.int64)
        _expect(self.whitening, "whitening", 2, np.float32)
        _expect(self.exits, "exits", 2, np.int64)
        if self.exits.shape[1] != 3:
            raise RoadmapError(f"exits must have shape (X, 3), got {self.exits.shape}")
        if len(self.exits):
            ends, classes = self.exits[:, :2], self.exits[:, 2]
            if (ends < 0).any() or (ends >= k).any() or (classes < 0).any():
                raise RoadmapError(
                    f"exits must hold node ids in 0..{k - 1} and action classes >= 0"
                )
            if len(np.unique(self.exits, axis=0)) != len(self.exits):
                raise RoadmapError("exits must be unique")
        dim = self.nodes.shape[1]
        if self.whitening.size and self.whitening.shape != (dim, dim):
            raise RoadmapError(
                f"whitening must have shape ({dim}, {dim}) or (0, 0), got {self.whitening.shape}"
            )
        if not np.isfinite(self.whitening).all():
            raise RoadmapError("whitening must be finite")
        if self.whitening.size and self.config.matching != "whitened":
            raise RoadmapError(f"whitening given, but the config matches by {self.config.matching}")
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
        if self.twins.shape[1] != 2:
            raise RoadmapError(f"twins must have shape (T, 2), got {self.twins.shape}")
        if len(self.twins):
            i, j = self.twins[:, 0], self.twins[:, 1]
            if (i < 0).any() or (j >= k).any() or (i >= j).any():
                raise RoadmapError(f"twins must be pairs i < j of node ids in 0..{k - 1}")
            if (np.diff(i * k + j) <= 0).any():
                raise RoadmapError("twins must be sorted and unique")
        if len(self.point_node) and ((self.point_node < -1).any() or (self.point_node >= k).any()):
            raise RoadmapError(f"point_node must hold -1 or node ids in 0..{k - 1}")
        if len(self.twins) and len(self.edges):
            group = self.twin_group
            joined = group[self.edges[:, 0]] == group[self.edges[:, 1]]
            if joined.any():
                i, j = self.edges[np.argmax(joined)].tolist()
                raise RoadmapError(f"twins must not be joined by an edge: edge ({i}, {j})")

    @property
    def num_nodes(self) -> int:
        return len(self.nodes)

    def nearest_node(self, z: np.ndarray) -> np.ndarray | int:
        """The node closest to a latent (D,) or to each of (M, D): in the roadmap's metric, or
        after whitening where the roadmap has one (fit_whitening)."""
        idx = self.nearest_nodes(z, 1)[..., 0]
        return int(idx) if idx.ndim == 0 else idx

    def nearest_nodes(self, z: np.ndarray, k: int) -> np.ndarray:
        """The k nodes closest to a latent (D,) or to each of (M, D), nearest first, measured
        as nearest_node measures: (k,) or (M, k) int64."""
        q = np.asarray(z, dtype=np.float64)
        dim = self.nodes.shape[1]
        if q.ndim not in (1, 2) or q.shape[-1] != dim:
            raise RoadmapError(f"z must have shape ({dim},) or (M, {dim}), got {q.shape}")
        if not np.isfinite(q).all():
            raise RoadmapError("z must be finite")
        if not self.num_nodes:
            raise RoadmapError("the roadmap has no nodes")
        if not 1 <= k <= self.num_nodes:
            raise RoadmapError(f"k must lie in 1..{self.num_nodes}, got {k}")
        p = metric_p(self.config.metric)
        if self.whitening.size:
            q, p = q @ self.whitening.astype(np.float64), 2
        if self._tree is None:
            nodes = self.nodes.astype(np.float64)
            self._tree = cKDTree(nodes @ self.whitening if self.whitening.size else nodes)
        _, idx = self._tree.query(q, k=[*range(1, k + 1)], p=p)
        return np.asarray(idx, dtype=np.int64)

    @property
    def component(self) -> np.ndarray:
        """Each node's connected component over the edges and twins: where paths can go."""
        if self._component is None:
            edges = np.concatenate([self.edges, self.twins])
            self._component = node_components(self.num_nodes, edges)
        return self._component

    def _twin_groups(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(each node's group, named by its smallest node id; the edges between groups, sorted
        and unique; their weights, summed over the edges they join), built once."""
        if self._groups is None:
            k = self.num_nodes
            group = twin_groups(k, self.twins)
            ends = np.sort(group[self.edges], axis=1)
            keep = ends[:, 0] != ends[:, 1]
            keys, index = np.unique(ends[keep, 0] * k + ends[keep, 1], return_inverse=True)
            weights = np.bincount(index, self.edge_weights[keep], len(keys)).astype(np.int64)
            self._groups = (group, np.column_stack([keys // k, keys % k]), weights)
        return self._groups

    @property
    def twin_group(self) -> np.ndarray:
        """Each node's twin group, named by its smallest node id (its own id without twins)."""
        return self._twin_groups()[0]

    @property
    def group_edges(self) -> np.ndarray:
        """(E', 2) the edges between twin groups (by their first nodes), i < j, sorted: the
        steps plans take (the edges themselves when there are no twins)."""
        return self._twin_groups()[1]

    @property
    def unshown(self) -> list[tuple[int, int]]:
        """Steps (from, to) between twin groups that no action pair took that way, where the
        config is one_way and the exits record the ways taken; [] otherwise."""
        if self._unshown is None:
            self._unshown = []
            if self.config.one_way and len(self.exits):
                group = self.twin_group
                shown = {(int(group[a]), int(group[b])) for a, b, _ in self.exits.tolist()}
                ways = [(a, b) for a, b in self.group_edges.tolist()]
                ways += [(b, a) for a, b in ways]
                self._unshown = sorted(set(ways) - shown)
        return self._unshown

    def _neighbour_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """CSR adjacency (indptr, indices) between twin groups, neighbours sorted ascending,
        built once."""
        if self._adjacency is None:
            edges = self._twin_groups()[1]
            rows = np.concatenate([edges[:, 0], edges[:, 1]])
            cols = np.concatenate([edges[:, 1], edges[:, 0]])
            order = np.lexsort((cols, rows))
            indptr = np.searchsorted(rows[order], np.arange(self.num_nodes + 1))
            self._adjacency = (indptr, cols[order])
        return self._adjacency

    def _steps(self, avoid: Iterable[tuple[int, int]]) -> list[tuple[int, int]]:
        """`avoid` as (from node, to node) pairs of valid node ids; RoadmapError otherwise."""
        steps = []
        for step in avoid:
            try:
                a, b = step
            except (TypeError, ValueError):
                raise RoadmapError(
                    f"avoid must hold steps (from node, to node), got {step!r}"
                ) from None
            steps.append((self._node_id(a, "avoid"), self._node_id(b, "avoid")))
        return steps

    def _hops(
        self, s: int, t: int, banned: list[tuple[int, int]]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The adjacency less the banned steps (indptr, indices), and every node's hops from
        s and to t over it."""
        indptr, indices = self._neighbour_arrays()
        if banned:
            indptr, indices = self._without(indptr, indices, np.array(banned, np.int64))
        graph = sparse.csr_matrix(
            (np.ones(len(indices)), indices, indptr), shape=(self.num_nodes, self.num_nodes)
        )
        hops = shortest_path(graph, directed=True, unweighted=True, indices=[s, t])
        from_s, to_t = hops[0], hops[1]
        if banned:  # no longer symmetric: hops to t run along the reversed steps
            to_t = shortest_path(graph.T.tocsr(), directed=True, unweighted=True, indices=t)
        return indptr, indices, from_s, to_t

    def _without(
        self, indptr: np.ndarray, indices: np.ndarray, steps: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The adjacency less the directed steps (S, 2) between the nodes' twin groups."""
        k = self.num_nodes
        rows = np.repeat(np.arange(k), np.diff(indptr))
        groups = self.twin_group[steps]
        keep = ~np.isin(rows * k + indices, groups[:, 0] * k + groups[:, 1])
        counts = np.bincount(rows[keep], minlength=k)
        return np.concatenate([[0], np.cumsum(counts)]), indices[keep]

    def _node_id(self, node: int, name: str) -> int:
        try:
            i = operator.index(node)
        except TypeError:
            raise RoadmapError(f"{name} must be an integer node id, got {node!r}") from None
        if not 0 <= i < self.num_nodes:
            raise RoadmapError(f"{name} must be a node id in 0..{self.num_nodes - 1}, got {i}")
        return i

    def neighbours(self, node: int) -> list[int]:
        """Twin groups (by their first node) sharing an edge with `node`'s, ascending."""
        i = self.twin_group[self._node_id(node, "node")]
        indptr, indices = self._neighbour_arrays()
        return indices[indptr[i] : indptr[i + 1]].tolist()

    def supports(self, path: list[int]) -> list[int]:
        """The action pairs behind each step of a path (its edges' weights, between twin
        groups)."""
        group, edges, weights = self._twin_groups()
        ids = np.asarray(path, dtype=np.int64)
        if len(ids) < 2:
            return []
        if (ids < 0).any() or (ids >= self.num_nodes).any():
            raise RoadmapError(f"path {path} takes a step that is not an edge")
        ids = group[ids]
        lo, hi = np.minimum(ids[:-1], ids[1:]), np.maximum(ids[:-1], ids[1:])
        k = self.num_nodes
        keys = edges[:, 0] * k + edges[:, 1]
        at = np.searchsorted(keys, lo * k + hi)  # edges are sorted and unique
        if (at >= len(keys)).any() or (keys[np.minimum(at, len(keys) - 1)] != lo * k + hi).any():
            raise RoadmapError(f"path {path} takes a step that is not an edge")
        return weights[at].tolist()

    def shortest_paths(
        self,
        src: int,
        dst: int,
        max_paths: int = 16,
        avoid: Iterable[tuple[int, int]] = (),
    ) -> list[list[int]]:
        """All shortest paths by hop count from src to dst, at most max_paths of them.

        Paths come in lexicographic order of their node ids, so the same roadmap always gives
        the same plans. [] when dst cannot be reached; [[src]] when src == dst or its twin.
        Twins count as one node: a path leaves from src and arrives at dst themselves, and
        passes each group between by its first node. `avoid`: steps (from node, to node), oldest
        first, that no path takes in that direction (a closed loop's steps whose action led
        elsewhere); where no path is left, only the steps without which none would be are let
        go (the newest kept first). A one_way roadmap's unshown steps come before them: paths
        take a step the data never showed only where nothing else reaches dst.
        """
        s = self._node_id(src, "src")
        t = self._node_id(dst, "dst")
        if isinstance(max_paths, bool) or not isinstance(max_paths, int) or max_paths < 1:
            raise RoadmapError(f"max_paths must be an integer >= 1, got {max_paths!r}")
        banned = [*self.unshown, *self._steps(avoid)]
        src_node, dst_node = s, t
        s, t = (int(g) for g in self.twin_group[[s, t]])
        if s == t:
            return [[src_node]]
        if self.turns:
            paths = self._memory_paths(s, t, banned, max_paths)
            return [[src_node, *p[1:-1], dst_node] for p in paths]
        indptr, indices, from_s, to_t = self._hops(s, t, banned)
        if not math.isfinite(from_s[t]):
            if not banned or not math.isfinite(self._hops(s, t, [])[2][t]):
                return []
            kept: list[tuple[int, int]] = []
            for step in reversed(banned):  # the newest first: each kept that leaves a way
                if math.isfinite(self._hops(s, t, [*kept, step])[2][t]):
                    kept.append(step)
            indptr, indices, from_s, to_t = self._hops(s, t, kept[::-1])

        def onward(u: int) -> list[int]:
            # Neighbours one hop further from src and one hop closer to dst: on a shortest path.
            nbrs = indices[indptr[u] : indptr[u + 1]]
            ok = (from_s[nbrs] == from_s[u] + 1) & (to_t[nbrs] == to_t[u] - 1)
            return nbrs[ok].tolist()

        found = walks(onward(s), onward, t, max_paths)  # smallest ids first: lexicographic
        return [[src_node, *path, dst_node] for path in found]

    @property
    def turns(self) -> Turns:
        """The turns a -> b -> c (twin groups) that the exits show no chain of moves takes
        (services.planner.exits); empty where every action leads to one node."""
        if self._turns is None:
            self._turns = forbidden_turns(self.exits, self.twin_group)
        return self._turns

    def _memory_paths(
        self, s: int, t: int, banned: list[tuple[int, int]], max_paths: int
    ) -> list[list[int]]:
        """shortest_paths between twin groups s != t, taking no forbidden turn; banned steps
        let go as shortest_paths lets them go."""
        indptr, indices = self._neighbour_arrays()
        group = self.twin_group

        def search(steps: list[tuple[int, int]], limit: int) -> list[list[int]]:
            pairs = [(int(group[a]), int(group[b])) for a, b in steps]
            return memory_paths(indptr, indices, self.turns, s, t, pairs, limit)

        paths = search(banned, max_paths)
        if paths or not banned or not search([], 1):
            return paths
        kept: list[tuple[int, int]] = []
        for step in reversed(banned):  # the newest first: each kept that leaves a way
            if search([*kept, step], 1):
                kept.append(step)
        return search(kept[::-1], max_paths)

    def save(self, directory: str | Path) -> None:
        """Write roadmap.safetensors (arrays) and roadmap.json (config, scalars, stats)."""
        out = Path(directory)
        out.mkdir(parents=True, exist_ok=True)
        # twins, whitening and exits only where there are some: a roadmap without them stays
        # readable by code from before they existed
        keys = (*_ARRAY_KEYS, *(k for k in _OPTIONAL_KEYS if getattr(self, k).size))
        arrays = {key: np.ascontiguousarray(getattr(self, key)) for key in keys}
        replace_atomically(out / ARRAYS_NAME, lambda tmp: save_file(arrays, str(tmp)))
        meta = {
            "format": FORMAT,
            "version": FORMAT_VERSION,
            "config": {
                k: v for k, v in asdict(self.config).items() if (k, v) not in _UNSAID_DEFAULTS
            },
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
            # Roadmaps saved before eps_rule existed were built with Algorithm 1's epsilon.
            # Those saved before matching existed matched in the metric.
            config = RoadmapConfig(**{"eps_rule": "paper", "matching": "metric"} | meta["config"])
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
                twins=arrays.get("twins", np.zeros((0, 2), np.int64)),
                whitening=arrays.get("whitening", np.zeros((0, 0), np.float32)),
                exits=arrays.get("exits", np.zeros((0, 3), np.int64)),
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
