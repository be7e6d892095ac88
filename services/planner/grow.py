"""`lsr roadmap grow`: a roadmap learns from experience without retraining the VAE.

The VAE and epsilon stay fixed. Growth is Algorithm 1's phases 2 and 3 over the roadmap's points
and the new ones together: the valid regions are the connected components of the epsilon-graph
of all of them, so a new image joins the region it falls in; a region holding built nodes is
one node (two built nodes that new images join become one, as building on all the data would
have made them), which keeps the built latent and its id, less the ids merged away; a region of
new images only becomes a node when it is as large as the pruning threshold (at least
NEW_NODE_MIN) and an action pair links it to the rest. Then every action pair's regions give the
edges. Guards against bad experience:
- a tuple with an image in no node is kept for review (`review/`), not added blindly; each
  growth tries it again, since more experience may place it;
- an executed action after which the scene is in the node it started from is a no-action
  observation, not an edge;
- an edge whose action, executed from its node, led elsewhere is contradicted; an edge with
  more contradictions than supporting pairs is dropped.
What the roadmap was built from (latents, reconstruction errors, actions, states) is kept beside
it in `members.safetensors`, so growth needs no training images.
"""

from __future__ import annotations

import json
import time
from collections import Counter, defaultdict
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
from services.planner.evaluate import label_nodes
from services.planner.knowing import FILE as MATCH_FILE
from services.planner.knowing import calibrate, save_calibration
from services.planner.members import MEMBERS, Members
from services.planner.regions import connected_regions
from services.planner.roadmap import ARRAYS_NAME, JSON_NAME, Roadmap
from shared.checkpoint import seal
from shared.dataset import FIELDS, Dataset, load_dataset
from shared.tasks import get_task
from shared.tasks.base import Task
from shared.tasks.spec import TaskSpec

REPORT = "growth.json"
REVIEW = "review"
# A new node needs at least this many images (or the roadmap's pruning threshold, if larger):
# one image outside every region is an outlier to review, not yet a state.
NEW_NODE_MIN = 3
_CDIST = {"l1": "cityblock", "l2": "euclidean", "inf": "chebyshev"}
_BLOCK = 1 << 22  # distances per block


def regions(
    points: np.ndarray, point_node: np.ndarray, k0: int, epsilon: float, metric: str, min_new: int
) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Phase 2 over all points, mapped onto the built nodes.

    point_node: the built node (of k0) of each point (-1: pruned, or new). Returns the node of every
    point (built ids; candidate new nodes numbered after them), the id each built node became
    (the smallest id of those its region joined), and the members of each candidate new node.
    """
    labels, _ = connected_regions(points.astype(np.float64), epsilon, metric)
    built = point_node >= 0
    owner = np.full(int(labels.max()) + 1, k0, np.int64)  # k0: no built node in the region
    np.minimum.at(owner, labels[built], point_node[built])
    became = np.arange(k0)
    became[point_node[built]] = owner[labels[built]]
    node = np.where(owner[labels] < k0, owner[labels], -1)
    order = np.argsort(labels, kind="stable")
    groups = np.split(order, np.cumsum(np.bincount(labels))[:-1])
    fresh = [g for g in groups if owner[labels[g[0]]] == k0 and len(g) >= min_new]
    for i, ids in enumerate(fresh):
        node[ids] = k0 + i
    return node, became, fresh


def _edges(node: np.ndarray, a: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Phase 3: (edges, weights) from the action pairs whose two points lie in two nodes."""
    n1, n2 = node[0::2], node[1::2]
    use = (a == 1) & (n1 >= 0) & (n2 >= 0) & (n1 != n2)
    lo, hi = np.minimum(n1, n2)[use], np.maximum(n1, n2)[use]
    keys, weights = np.unique(lo * k + hi, return_counts=True)
    return np.stack([keys // k, keys % k], axis=1).astype(np.int64), weights.astype(np.int64)


def contradictions(
    task: Task, node: np.ndarray, members: Members, new: np.ndarray
) -> Counter[tuple[int, int]]:
    """Per edge (i < j), how many of the `new` action tuples contradict it: the same action
    (by the task), executed from one of its ends, led somewhere other than its other end."""
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
        for other in leaving.get(start, ()):
            target = int(n2[other])
            if (
                other != t
                and target != end
                and task.same_action(members.actions[t], members.actions[other])
            ):
                found[(min(start, target), max(start, target))] += 1
    return found


def components(k: int, edges: np.ndarray) -> int:
    graph = sparse.csr_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(k, k))
    return int(connected_components(graph, directed=False)[0]) if k else 0


def grow(
    roadmap: Roadmap, members: Members, new: Members, task: Task
) -> tuple[Roadmap, Members, dict[str, Any]]:
    """The grown roadmap, its members (old then new) and what happened, as counts."""
    started = time.perf_counter()
    metric, epsilon = roadmap.config.metric, roadmap.epsilon
    k0 = roadmap.num_nodes
    everything = members + new
    base = len(members.points)
    point_node = np.concatenate([roadmap.point_node, np.full(len(new.points), -1, np.int64)])
    built_min = roadmap.config.min_samples or int(roadmap.stats.get("min_samples", 1))
    node, became, fresh = regions(
        everything.points, point_node, k0, epsilon, metric, max(NEW_NODE_MIN, built_min)
    )
    # A new node needs an action pair linking it to the rest (the builder prunes isolated ones).
    edges, _ = _edges(node, everything.a, k0 + len(fresh))
    linked = np.zeros(k0 + len(fresh), bool)
    linked[edges.ravel()] = True
    keep = np.zeros(k0 + len(fresh), bool)
    keep[np.unique(became)] = True  # built nodes, less those merged into another
    keep[k0:] = linked[k0:]
    for ids, kept in zip(fresh, keep[k0:], strict=True):
        if not kept:
            node[ids] = -1
    renumber = np.cumsum(keep) - 1
    node = np.where(node >= 0, renumber[np.maximum(node, 0)], -1)
    k = int(keep.sum())
    edges, weights = _edges(node, everything.a, k)

    # Experience that contradicts an edge; an edge contradicted more than supported goes.
    tuples_new = np.arange(base // 2, len(everything.a))
    against = contradictions(task, node, everything, tuples_new)
    weight_of = {(int(i), int(j)): int(w) for (i, j), w in zip(edges, weights, strict=True)}
    dropped = sorted(e for e, c in against.items() if e in weight_of and c > weight_of[e])
    if dropped:
        gone = {i * k + j for i, j in dropped}
        keep_edge = np.array([i * k + j not in gone for i, j in edges.tolist()], bool)
        edges, weights = edges[keep_edge], weights[keep_edge]

    # Held for review: new tuples with an image in no node.
    n1, n2 = node[0::2], node[1::2]
    held = tuples_new[(n1[tuples_new] < 0) | (n2[tuples_new] < 0)]
    moved = new.a == 1
    same_node = moved & (n1[tuples_new] >= 0) & (n1[tuples_new] == n2[tuples_new])

    # A merged node keeps the latent of its largest built part; a new one, the member closest
    # to its mean (as the builder picks).
    largest = {}
    for old in np.argsort(-roadmap.node_sizes, kind="stable").tolist():
        largest.setdefault(int(became[old]), old)
    nodes = np.concatenate(
        [roadmap.nodes[[largest[int(b)] for b in np.flatnonzero(keep[:k0])]]]
        + [
            everything.points[_representative(everything.points, ids, metric)][None]
            for ids, kept in zip(fresh, keep[k0:], strict=True)
            if kept
        ]
    ).astype(np.float32)
    sizes = np.bincount(node[node >= 0], minlength=k).astype(np.int64)
    old_ids = renumber[became]  # where each built node is now
    old_edges = {(int(old_ids[i]), int(old_ids[j])) for i, j in roadmap.edges}
    report = {
        "tuples": len(new.a),
        "action_pairs": int(moved.sum()),
        "images_joined": int((node[base:] >= 0).sum()),
        "merged_nodes": int(k0 - keep[:k0].sum()),
        "new_nodes": int(keep[k0:].sum()),
        "new_edges": len({(int(i), int(j)) for i, j in edges} - old_edges),
        "edge_weight_added": int(weights.sum() - roadmap.edge_weights.sum()),
        "no_change": int(same_node.sum()),
        "held_for_review": len(held),
        "contradicted_edges": len([e for e in against if e in weight_of]),
        "contradictions": int(sum(c for e, c in against.items() if e in weight_of)),
        "dropped_edges": [list(e) for e in dropped],
        "nodes": [k0, k],
        "edges": [len(roadmap.edges), len(edges)],
        "components": [components(k0, roadmap.edges), components(k, edges)],
        "seconds": time.perf_counter() - started,
    }
    stats = {**roadmap.stats, "nodes": k, "edges": len(edges), "edge_weight": int(weights.sum())}
    stats["points"] = len(node)
    stats["grown"] = [
        *roadmap.stats.get("grown", []),
        {k_: v for k_, v in report.items() if k_ != "seconds"},
    ]
    grown = Roadmap(
        config=roadmap.config,
        epsilon=epsilon,
        mu0=roadmap.mu0,
        sigma0=roadmap.sigma0,
        nodes=nodes,
        node_sizes=np.maximum(sizes, 1),
        edges=edges,
        edge_weights=weights,
        point_node=node.astype(np.int64),
        stats=stats,
    )
    report["held"] = held - base // 2  # indices into the new tuples
    return grown, everything, report


def _representative(points: np.ndarray, ids: np.ndarray, metric: str) -> int:
    """The member closest to the region mean, as the builder picks a node's latent."""
    mean = points[ids].mean(axis=0, keepdims=True)
    return int(ids[np.argmin(cdist(points[ids], mean, _CDIST[metric])[:, 0])])


def load_members(model_dir: Path, vae: VAE, data_dir: Path | str | None = None) -> Members:
    """The current version's members; a roadmap built before they were kept encodes its
    training data (`data_dir`, else the path the VAE recorded) once."""
    folder = versions.roadmap_dir(model_dir)
    if (folder / MEMBERS).is_file():
        members = Members.load(folder)
    else:
        path = data_dir or read_vae_config(model_dir / "vae")["dataset"]["path"]
        members = Members.encode(vae, load_dataset(path))
    points = len(Roadmap.load(folder).point_node)
    if len(members.points) != points:
        raise ValueError(
            f"{folder}: the roadmap has {points} points, its members {len(members.points)}; "
            "give the model's training data with --data"
        )
    return members


def _experience(
    vae: VAE, task: Task, folders: list[Path], size: int, used: dict[str, int]
) -> tuple[Members, list[Dataset], dict[str, int]]:
    """The tuples of each folder that the roadmap has not grown from yet (`used`: tuples
    already taken, by resolved path), encoded; and the new counts."""
    parts: list[Members] = []
    found: list[Dataset] = []
    taken = dict(used)
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
        part = Dataset(data.manifest, *(getattr(data, f)[start:] for f in FIELDS))
        parts.append(Members.encode(vae, part))
        found.append(part)
    if not parts:
        raise ValueError(
            f"nothing new in {[str(f) for f in folders]}: the roadmap grew from all of it"
        )
    total = parts[0]
    for part in parts[1:]:
        total = total + part
    return total, found, taken


def grow_model(
    model_dir: Path | str, experience: list[Path | str], data_dir: Path | str | None = None
) -> dict[str, Any]:
    """Grow the model's current roadmap by the experience folders (the tuples it has not grown
    from yet) into a new current version; the report of what happened."""
    model_dir = Path(model_dir)
    vae, config = load_vae(model_dir / "vae")
    task = get_task(config["dataset"]["task"])
    source = versions.current_version(model_dir)
    roadmap = Roadmap.load(versions.roadmap_dir(model_dir))
    members = load_members(model_dir, vae, data_dir)
    size = config["model"]["image_size"]
    used = roadmap.stats.get("experience", {})
    new, datasets, used = _experience(vae, task, [Path(f) for f in experience], size, used)
    grown, everything, report = grow(roadmap, members, new, task)
    grown.stats["experience"] = used

    name = versions.next_version(model_dir)
    partial = versions.staging_dir(model_dir, name)
    grown.save(partial)
    joined = grown.point_node >= 0
    calibration = calibrate(grown, everything.points[joined], everything.errors[joined])
    save_calibration(calibration, partial)
    everything.save(partial)
    if everything.has_state.any():
        with_state = np.where(everything.has_state.astype(bool), grown.point_node, -1)
        labels = label_nodes(with_state, everything.states, grown.num_nodes)
        (partial / LABELS).write_text(json.dumps(labels.to_json(task)) + "\n")
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
        spec = TaskSpec(spec.task, spec.action, None)
    log = ExperienceLog(folder, spec, size, source="review")
    log.append(columns["image1"][held], columns["image2"][held], columns["u"][held], *states)
