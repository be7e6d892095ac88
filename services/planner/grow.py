"""`lsr roadmap grow`: a roadmap learns from experience without retraining the VAE.

The VAE, epsilon, the built nodes (their ids and latents) and what each node is known by stay
fixed. A new image joins the node the planner would match it to, where it is known there (the
calibrated knowing test of `services.planner.knowing`: growth and planning place an image
alike) and lies within the same-state radius of an image already there (`same_state_radius`:
the knowing bound refuses other worlds, not neighbouring states). The other images form
regions among themselves by that radius, and a region as large as the pruning threshold (at
least NEW_NODE_MIN images) that an action pair links to another node becomes a new node. Then
every action pair's nodes give the edges, as Algorithm 1's phase 3. Guards against bad experience:
- a tuple with an image in no node is kept for review (`review/`), not added blindly; each
  growth tries it again, since more experience may place it;
- an executed action after which the scene is in the node it started from is a no-action
  observation, not an edge;
- an edge whose action, executed from its node, led to an image of another state (farther
  than the same-state radius) is contradicted; one contradicted more often than its pairs
  support it is flagged in the report (not dropped: twins make false contradictions);
- a no-action pair whose images lie in two nodes shows them to be one state (twins, which
  Algorithm 1's phase 1 would have joined into one node; built nodes keep their ids, so the
  roadmap records the pair and plans over the groups), unless an edge joins the two groups:
  an action pair between them says they differ, and the link is refused.
What the roadmap was built from (latents, reconstruction errors, actions, states) is kept beside
it in `members.safetensors`, so growth needs no training images.
"""

from __future__ import annotations

import json
import time
from collections import Counter, defaultdict
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components
from scipy.spatial.distance import cdist

from services.data.experience import ExperienceLog
from services.encoder.checkpoint import load_vae, read_vae_config
from services.encoder.model import VAE
from services.planner import versions
from services.planner.build import LABELS
from services.planner.evaluate import NodeLabels, label_nodes
from services.planner.exits import action_exits
from services.planner.knowing import FILE as MATCH_FILE
from services.planner.knowing import Calibration, load_calibration, match, save_calibration
from services.planner.members import MEMBERS, Members, tuple_keys
from services.planner.regions import CDIST_NAME, connected_regions
from services.planner.roadmap import (
    ARRAYS_NAME,
    JSON_NAME,
    Roadmap,
    pair_distances,
    whitening_for,
)
from shared.checkpoint import seal
from shared.dataset import FIELDS, Dataset, load_dataset
from shared.graphs import node_components
from shared.tasks import get_task
from shared.tasks.base import Task

REPORT = "growth.json"
REVIEW = "review"
# A new node needs at least this many images (or the roadmap's pruning threshold, if larger):
# one image outside every region is an outlier to review, not yet a state.
NEW_NODE_MIN = 3


def fresh_regions(
    points: np.ndarray,
    loose: np.ndarray,
    epsilon: float,
    metric: str,
    min_new: int,
    links: np.ndarray | None = None,
) -> list[np.ndarray]:
    """Regions (Algorithm 1's phase 2) among the points no node holds (`loose`, ascending);
    those of at least `min_new` members, as indices into `points`. `links` (L, 2): pairs of
    points that are one region however far apart (no-action pairs, as phase 1 joins them)."""
    if not len(loose):
        return []
    labels, _ = connected_regions(points[loose].astype(np.float64), epsilon, metric)
    if links is not None and len(links):
        at = np.searchsorted(loose, links)
        inside = (at < len(loose)) & (loose[np.minimum(at, len(loose) - 1)] == links)
        at = at[inside.all(1)]
        first = np.unique(labels, return_index=True)[1]  # a point of each region
        ends = np.concatenate([at, np.column_stack([np.arange(len(loose)), first[labels]])])
        n = len(loose)
        graph = sparse.csr_matrix((np.ones(len(ends)), (ends[:, 0], ends[:, 1])), shape=(n, n))
        labels = connected_components(graph, directed=False)[1]
    order = np.argsort(labels, kind="stable")
    groups = np.split(loose[order], np.cumsum(np.bincount(labels))[:-1])
    return [g for g in groups if len(g) >= min_new]


def same_state_radius(members: Members, metric: str, fallback: float) -> float:
    """How far apart two images of one state may lie, from the training pairs alone: the
    geometric mean of the no-action pairs' 99th percentile distance (one state, seen twice) and
    the action pairs' 1st percentile (two states one move apart). The knowing bound cannot tell
    states apart (box stacking at 500 tuples: 21.8, where the nearest image of another state
    lies 5.9-9.0 away and of the same state 0.9-4.1; this rule gives 3.9). `fallback` (the
    roadmap's epsilon) where the data has no pairs of one kind."""
    built = ~np.asarray(members.experience, bool)
    first, second = members.points[0::2][built], members.points[1::2][built]
    gaps = pair_distances(first, second, metric)
    moved = members.a[built] == 1
    if moved.all() or not moved.any():
        return fallback
    return float(np.sqrt(np.quantile(gaps[~moved], 0.99) * np.quantile(gaps[moved], 0.01)))


def near_members(
    points: np.ndarray,
    node: np.ndarray,
    ids: np.ndarray,
    to: np.ndarray,
    radius: float,
    metric: str,
) -> np.ndarray:
    """For each point `ids[i]`, whether some point already in node `to[i]` lies within
    `radius` of it (False where `to[i]` < 0)."""
    near = np.zeros(len(ids), bool)
    for target in np.unique(to[to >= 0]):
        mine = np.flatnonzero(to == target)
        there = points[np.flatnonzero(node == target)]
        if not len(there):
            continue
        gaps = cdist(points[ids[mine]], there, CDIST_NAME[metric])
        near[mine] = gaps.min(axis=1) <= radius
    return near


def _edges(node: np.ndarray, a: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Phase 3: (edges, weights) from the action pairs whose two points lie in two nodes."""
    n1, n2 = node[0::2], node[1::2]
    use = (a == 1) & (n1 >= 0) & (n2 >= 0) & (n1 != n2)
    lo, hi = np.minimum(n1, n2)[use], np.maximum(n1, n2)[use]
    keys, weights = np.unique(lo * k + hi, return_counts=True)
    return np.stack([keys // k, keys % k], axis=1).astype(np.int64), weights.astype(np.int64)


def twin_links(
    node: np.ndarray, a: np.ndarray, edges: np.ndarray, known: np.ndarray, k: int
) -> tuple[np.ndarray, int]:
    """(the twin pairs (T, 2), i < j, sorted: `known` ones and those the no-action pairs show;
    how many links were refused because an edge would join a group to itself). Known links
    are tried first: paths already given rely on them."""
    n1, n2 = node[0::2], node[1::2]
    shown = (a == 0) & (n1 >= 0) & (n2 >= 0) & (n1 != n2)
    pairs = np.unique(
        np.column_stack([np.minimum(n1, n2)[shown], np.maximum(n1, n2)[shown]]), axis=0
    )
    known = np.asarray(known, np.int64).reshape(-1, 2)
    fresh = pairs[~np.isin(pairs[:, 0] * k + pairs[:, 1], known[:, 0] * k + known[:, 1])]
    candidates = np.concatenate([known, fresh]).astype(np.int64)
    group = np.arange(k)
    kept, refused = [], 0
    for i, j in candidates:
        gi, gj = group[i], group[j]
        if gi != gj and np.isin(group[edges], (gi, gj)).all(1).any():
            refused += 1
            continue
        group[group == gj] = gi
        kept.append((i, j))
    return np.unique(np.asarray(kept, np.int64).reshape(-1, 2), axis=0), refused


def contradictions(
    task: Task, node: np.ndarray, members: Members, new: np.ndarray, radius: float, metric: str
) -> Counter[tuple[int, int]]:
    """Per edge (i < j), how many of the `new` action tuples contradict it: the same action
    (by the task), executed from one of its ends, led somewhere other than its other end, and
    to an image farther than `radius` from the one it led to there (two nodes of one state,
    twins, are no contradiction)."""
    n1, n2 = node[0::2], node[1::2]
    known = (members.a == 1) & (n1 >= 0) & (n2 >= 0) & (n1 != n2)
    leaving: dict[int, list[int]] = defaultdict(list)
    for t in np.flatnonzero(known).tolist():
        leaving[int(n1[t])].append(t)
    found: Counter[tuple[int, int]] = Counter()
    for t in new.tolist():
        start, end = int(n1[t]), int(n2[t])
        if members.a[t] != 1 or start < 0 or end < 0:
            continue
        after = members.points[2 * t + 1]
        targets = {  # each tuple counts once against each edge it contradicts
            int(n2[other])
            for other in leaving.get(start, ())
            if other != t
            and int(n2[other]) != end
            and task.same_action(members.actions[t], members.actions[other])
            and pair_distances(members.points[2 * other + 1], after, metric) > radius
        }
        for target in targets:
            found[(min(start, target), max(start, target))] += 1
    return found


def components(k: int, edges: np.ndarray) -> int:
    return int(node_components(k, edges).max()) + 1 if k else 0


def state_labels(roadmap: Roadmap, members: Members, task: Task) -> NodeLabels:
    """Each node's majority view over its images that came with a true state (a robot's do
    not)."""
    known = np.where(members.has_state.astype(bool), roadmap.point_node, -1)
    return label_nodes(known, members.states, roadmap.num_nodes, task)


def grow(
    roadmap: Roadmap, calibration: Calibration, members: Members, new: Members, task: Task
) -> tuple[Roadmap, Calibration, Members, dict[str, Any]]:
    """The grown roadmap, what it knows, its members (old then new) and what happened."""
    started = time.perf_counter()
    k0 = roadmap.num_nodes
    new = replace(new, experience=np.ones(len(new.a), np.uint8))
    everything = members + new
    base = len(members.points)
    metric = roadmap.config.metric
    # Every image without a node (new ones, and those held or pruned before) is matched.
    node = np.concatenate([roadmap.point_node, np.full(len(new.points), -1, np.int64)])
    radius = same_state_radius(members, metric, roadmap.epsilon)
    loose = np.flatnonzero(node < 0)
    found = match(roadmap, calibration, everything.points[loose], everything.errors[loose])
    matched = np.array([m.node if m.known else -1 for m in found], np.int64)
    # Known at its node is not enough: that bound refuses other worlds, not other states.
    close = near_members(everything.points, node, loose, matched, radius, metric)
    node[loose] = np.where(close, matched, -1)
    # A no-action pair is one state seen twice (Algorithm 1's phase 1 joins the two): an image
    # of this world (known at its nearest node) without a node joins its partner's node, and
    # a pair of two images without a node holds together in new regions.
    partner = np.arange(len(node)) ^ 1
    still = np.repeat(everything.a == 0, 2)
    known = np.zeros(len(node), bool)
    known[loose] = matched >= 0
    glued = still & known & (node < 0) & (node[partner] >= 0)
    node[glued] = node[partner[glued]]
    built_min = roadmap.config.min_samples or int(roadmap.stats.get("min_samples", 1))
    pairs = np.flatnonzero(still[0::2] & (node[0::2] < 0) & (node[1::2] < 0))
    fresh = fresh_regions(
        everything.points,
        np.flatnonzero(node < 0),
        radius,
        metric,
        max(NEW_NODE_MIN, built_min),
        np.column_stack([2 * pairs, 2 * pairs + 1]),
    )
    for i, ids in enumerate(fresh):
        node[ids] = k0 + i
    # A new node needs an action pair linking it to another (the builder prunes isolated ones).
    edges, _ = _edges(node, everything.a, k0 + len(fresh))
    linked = np.zeros(k0 + len(fresh), bool)
    linked[edges.ravel()] = True
    fresh = [ids for i, ids in enumerate(fresh) if linked[k0 + i]]
    node[node >= k0] = -1
    for i, ids in enumerate(fresh):
        node[ids] = k0 + i
    k = k0 + len(fresh)
    edges, weights = _edges(node, everything.a, k)
    twins, twins_refused = twin_links(node, everything.a, edges, roadmap.twins, k)

    # Experience that contradicts an edge is flagged, not acted on: in box stacking at 500
    # tuples every edge dropped for it (contradicted more often than supported) was legal, the
    # outcomes being another node of the same state (twins) beyond the same-state radius.
    tuples_new = np.arange(base // 2, len(everything.a))
    against = contradictions(
        task, node, everything, np.flatnonzero(everything.experience), radius, metric
    )
    weight_of = {(int(i), int(j)): int(w) for (i, j), w in zip(edges, weights, strict=True)}
    flagged = sorted(
        [i, j, c, weight_of[(i, j)]]
        for (i, j), c in against.items()
        if c > weight_of.get((i, j), c)
    )

    # Held for review: new tuples with an image in no node.
    n1, n2 = node[0::2], node[1::2]
    held = tuples_new[(n1[tuples_new] < 0) | (n2[tuples_new] < 0)]
    moved = new.a == 1
    same_node = moved & (n1[tuples_new] >= 0) & (n1[tuples_new] == n2[tuples_new])

    reps = [everything.points[_representative(everything.points, ids, metric)] for ids in fresh]
    reps = np.reshape(reps, (-1, roadmap.nodes.shape[1]))
    nodes = np.concatenate([roadmap.nodes, reps]).astype(np.float32)
    sizes = np.bincount(node[node >= 0], minlength=k).astype(np.int64)
    old_edges = {(int(i), int(j)) for i, j in roadmap.edges}
    report = {
        "tuples": len(new.a),
        "action_pairs": int(moved.sum()),
        "images_joined": int((node[base:] >= 0).sum()),
        "images_known": int(sum(m.known for m in found)),  # of those without a node
        "images_known_elsewhere": int(((matched >= 0) & ~close).sum()),  # no member near
        "images_joined_by_partner": int(glued.sum()),
        "same_state_radius": radius,
        "new_nodes": len(fresh),
        "new_edges": len({(int(i), int(j)) for i, j in edges} - old_edges),
        "edge_weight_added": int(weights.sum() - roadmap.edge_weights.sum()),
        "no_change": int(same_node.sum()),
        "held_for_review": len(held),
        "contradicted_edges": len([e for e in against if e in weight_of]),
        "contradictions": int(sum(c for e, c in against.items() if e in weight_of)),
        # [i, j, contradictions, supporting pairs]: contradicted more often than supported
        "flagged_edges": flagged,
        "twins": [len(roadmap.twins), len(twins)],
        "twins_refused": twins_refused,
        "nodes": [k0, k],
        "edges": [len(roadmap.edges), len(edges)],
        "components": [
            components(k0, np.concatenate([roadmap.edges, roadmap.twins])),
            components(k, np.concatenate([edges, twins])),
        ],
        "seconds": time.perf_counter() - started,
    }
    stats = {**roadmap.stats, "nodes": k, "edges": len(edges), "edge_weight": int(weights.sum())}
    stats["twins"] = len(twins)
    stats["points"] = len(node)
    stats["grown"] = [
        *roadmap.stats.get("grown", []),
        {k_: v for k_, v in report.items() if k_ != "seconds"},
    ]
    grown = Roadmap(
        config=roadmap.config,
        epsilon=roadmap.epsilon,
        mu0=roadmap.mu0,
        sigma0=roadmap.sigma0,
        nodes=nodes,
        node_sizes=np.maximum(sizes, 1),
        edges=edges,
        edge_weights=weights,
        point_node=node.astype(np.int64),
        stats=stats,
        twins=twins,
        whitening=whitening_for(roadmap.config, everything.points, node),
        # where actions lead, experience included: kept only by roadmaps built with exits
        exits=action_exits(node, everything.a, everything.actions, task.same_action)
        if len(roadmap.exits)
        else roadmap.exits,
    )
    report["held"] = held - base // 2  # indices into the new tuples
    # Built nodes are known as before (recalibrating on what they let in would let the bounds
    # creep outward growth after growth); a new node by the pooled bound, as a small one.
    thresholds = calibration.node_thresholds + (calibration.threshold,) * len(fresh)
    return grown, replace(calibration, node_thresholds=thresholds), everything, report


def _representative(points: np.ndarray, ids: np.ndarray, metric: str) -> int:
    """The member closest to the region mean, as the builder picks a node's latent."""
    mean = points[ids].mean(axis=0, keepdims=True)
    return int(ids[np.argmin(pair_distances(points[ids], mean, metric))])


# Share of built images nearest their own node, for data to be the roadmap's: all of them for
# every shipped model, 0.6% for other box data; a test's one-epoch VAE, whose nodes overlap,
# puts 75% of its own images there and 7% of other data's.
OWN_NODE_MIN = 0.5


def load_members(
    model_dir: Path, vae: VAE, data_dir: Path | str | None = None, folder: Path | None = None
) -> Members:
    """The members of a roadmap version (default: the current one); a roadmap built before
    they were kept encodes its training data (`data_dir`, else the VAE's recorded path) once."""
    folder = folder or versions.roadmap_dir(model_dir)
    roadmap = Roadmap.load(folder)
    points = len(roadmap.point_node)
    if (folder / MEMBERS).is_file():
        members = Members.load(folder)
        if len(members.points) != points:
            raise ValueError(
                f"{folder / MEMBERS}: {len(members.points)} points, its roadmap {points}: the "
                "file does not belong to this roadmap; rebuild it with lsr build-roadmap"
            )
        return members
    path = data_dir or read_vae_config(model_dir / "vae")["dataset"]["path"]
    members = Members.encode(vae, load_dataset(path))
    if len(members.points) != points:
        raise ValueError(
            f"{path}: {len(members.points)} images, the roadmap in {folder} was built on "
            f"{points}; give the model's training data with --data"
        )
    # Same count, other images (data generated again with other options): a roadmap's built
    # images lie nearest their own node (all of them for every model here), others do not
    # (0.6% for the box data generated with --starts balanced instead of random).
    kept = roadmap.point_node >= 0
    if not kept.any():
        return members
    own = np.atleast_1d(roadmap.nearest_node(members.points[kept])) == roadmap.point_node[kept]
    if own.mean() < OWN_NODE_MIN:
        raise ValueError(
            f"{path}: only {100 * own.mean():.1f}% of its images lie nearest the node the "
            f"roadmap in {folder} gave them: not the data it was built on; give the model's "
            "training data with --data (its REPORT.md says how it was generated)"
        )
    return members


def _experience(
    vae: VAE,
    task: Task,
    folders: list[Path],
    size: int,
    used: dict[str, int],
    known: np.ndarray,
) -> tuple[Members, list[Dataset], dict[str, int], int]:
    """The tuples of each folder that the roadmap has not grown from yet, encoded; the new
    counts; how many were skipped as tuples the roadmap already holds. A folder's tuples
    already taken are skipped by path (`used`: their count, by resolved path), any other
    tuple by its content (`known`: the members' keys), so that a copy counts once too."""
    parts: list[Members] = []
    found: list[Dataset] = []
    taken = dict(used)
    seen = {int(k) for k in known if k}
    again = 0
    for folder in folders:
        data = load_dataset(folder)
        if data.task != task.name or data.spec.action != task.spec.action:
            raise ValueError(
                f"{folder}: holds {data.task!r} experience, the model plans {task.name!r}"
            )
        if data.image_size != size:
            raise ValueError(f"{folder}: {data.image_size} px images, the model takes {size} px")
        key = str(Path(folder).resolve())
        start = taken.get(key, 0)
        taken[key] = len(data)
        if start >= len(data):
            continue
        keys = tuple_keys(data.image1[start:], data.image2[start:], data.u[start:])
        fresh = np.zeros(len(keys), bool)
        for i, content in enumerate(keys.tolist()):
            fresh[i] = content not in seen
            seen.add(content)
        again += int((~fresh).sum())
        if not fresh.any():
            continue
        keep = start + np.flatnonzero(fresh)
        part = Dataset(data.manifest, *(getattr(data, f)[keep] for f in FIELDS))
        parts.append(Members.encode(vae, part, keys[fresh]))
        found.append(part)
    if not parts:
        held = f" ({again} tuples it holds already or twice: a copy?)" if again else ""
        raise ValueError(
            f"nothing new in {[str(f) for f in folders]}: the roadmap grew from all of it{held}"
        )
    total = parts[0]
    for part in parts[1:]:
        total = total + part
    return total, found, taken, again


def grow_model(
    model_dir: Path | str,
    experience: list[Path | str],
    data_dir: Path | str | None = None,
) -> dict[str, Any]:
    """Grow the model's current roadmap by the experience folders (the tuples it has not grown
    from yet) into a new current version; the report of what happened. One growth at a time
    per model (a lock), from one version read once."""
    model_dir = Path(model_dir)
    with versions.growing(model_dir):
        return _grow_model(model_dir, experience, data_dir)


def _grow_model(
    model_dir: Path, experience: list[Path | str], data_dir: Path | str | None
) -> dict[str, Any]:
    vae, config = load_vae(model_dir / "vae")
    task = get_task(config["dataset"]["task"])
    source = versions.current_version(model_dir)
    folder = versions.version_dir(model_dir, source)
    roadmap = Roadmap.load(folder)
    calibration = load_calibration(folder, roadmap)
    members = load_members(model_dir, vae, data_dir, folder)
    size = config["model"]["image_size"]
    used = roadmap.stats.get("experience", {})
    new, datasets, used, again = _experience(
        vae, task, [Path(f) for f in experience], size, used, members.keys
    )
    grown, calibration, everything, report = grow(roadmap, calibration, members, new, task)
    report["already_held"] = again
    grown.stats["experience"] = used

    name = versions.next_version(model_dir)
    partial = versions.staging_dir(model_dir, name)
    grown.save(partial)
    save_calibration(calibration, partial)
    everything.save(partial)
    labels = state_labels(grown, everything, task)
    if everything.has_state.any() and labels.members.all():
        (partial / LABELS).write_text(json.dumps(labels.to_json(task)) + "\n")
    elif everything.has_state.any():  # a new node of a robot's images only: no state to name
        report["labels"] = (
            f"none: nodes {np.flatnonzero(labels.members == 0).tolist()} have no state"
        )
    held = report.pop("held")
    if len(held):
        _write_review(partial / REVIEW, datasets, held, size)
    report |= {"from": source, "version": name, "experience": used}
    (partial / REPORT).write_text(json.dumps(report, indent=2) + "\n")
    seal(partial, [ARRAYS_NAME, JSON_NAME, MATCH_FILE, MEMBERS])
    versions.publish(model_dir, name, partial)
    return report


def _write_review(folder: Path, datasets: list[Dataset], held: np.ndarray, size: int) -> None:
    """The held tuples, as an experience folder a person can look at (or export)."""
    columns = {
        f: np.concatenate([getattr(d, f) for d in datasets]) for f in ("image1", "image2", "u")
    }
    spec = datasets[0].spec
    states: tuple[np.ndarray, ...] = ()
    if all(d.spec == spec for d in datasets) and spec.state is not None:
        states = tuple(
            np.concatenate([getattr(d, f) for d in datasets])[held] for f in ("state1", "state2")
        )
    else:  # experience with and without states: the review keeps none
        spec = replace(spec, state=None)
    log = ExperienceLog(folder, spec, size, source="review")
    log.append(columns["image1"][held], columns["image2"][held], columns["u"][held], *states)
