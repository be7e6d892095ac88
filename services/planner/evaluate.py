"""The paper's Table I, automatically: plan between unseen images and check every step.

A node's true state is the majority state of its training members. A path is correct when its
first node shows the start state, its last the goal state, and every step is one legal move.
"""

from __future__ import annotations

import itertools
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from services.planner.knowing import Calibration, connect
from services.planner.roadmap import Roadmap, pair_distances
from shared.tasks import get_task
from shared.tasks.base import IllegalActionError, Task, optimal_moves


@dataclass
class NodeLabels:
    """Majority state array of each node's members, and the share that agrees with it."""

    states: np.ndarray  # (K, *spec.state.shape) of spec.state.dtype
    purity: np.ndarray  # (K,) float
    members: np.ndarray  # (K,) int

    def to_json(self, task: Task) -> list[dict[str, Any]]:
        return [
            {
                "node": i,
                "state": task.state_to_json(task.array_to_state(s)),
                "purity": float(p),
                "members": int(m),
            }
            for i, (s, p, m) in enumerate(zip(self.states, self.purity, self.members, strict=True))
        ]

    @classmethod
    def from_json(cls, task: Task, rows: list[dict[str, Any]]) -> NodeLabels:
        spec = task.spec.state
        assert spec is not None, "node labels need a task with states"
        states = [task.state_to_array(task.parse_state(r["state"])) for r in rows]
        return cls(
            states=np.array(states, spec.dtype).reshape(len(rows), *spec.shape),
            purity=np.array([r["purity"] for r in rows]),
            members=np.array([r["members"] for r in rows]),
        )


def label_nodes(point_node: np.ndarray, point_states: np.ndarray, num_nodes: int) -> NodeLabels:
    """point_states: (2N, *state_shape) for the points numbered z1[0], z2[0], z1[1], ..."""
    shape = point_states.shape[1:]
    keys = [s.tobytes() for s in point_states]
    states = np.zeros((num_nodes, *shape), point_states.dtype)
    purity = np.zeros(num_nodes)
    members = np.zeros(num_nodes, np.int64)
    groups: dict[int, Counter] = {}
    for node, key in zip(point_node.tolist(), keys, strict=True):
        if node >= 0:
            groups.setdefault(node, Counter())[key] += 1
    for node, counter in groups.items():
        key, count = counter.most_common(1)[0]
        states[node] = np.frombuffer(key, point_states.dtype).reshape(shape)
        members[node] = sum(counter.values())
        purity[node] = count / members[node]
    return NodeLabels(states, purity, members)


class TransitionChecker:
    """Is t one legal move from s? Neighbour sets cached per state."""

    def __init__(self, task: Task) -> None:
        self.task = task
        self._next: dict[Any, set[Any]] = {}

    def legal(self, s: Any, t: Any) -> bool:
        if s is None or t is None:  # an image that shows no valid state
            return False
        if s not in self._next:
            self._next[s] = {n for _, n in self.task.neighbours(s)}
        return t in self._next[s]


def action_leads(task: Task, state: Any, action: Any, target: Any) -> bool:
    """The action, applied by the task's rules to `state`, gives `target` (None never does)."""
    try:
        return action is not None and task.apply(state, action) == target
    except IllegalActionError:
        return False


def path_verdict(
    checker: TransitionChecker, states: list[Any], start: Any, goal: Any
) -> tuple[bool, int, int]:
    """(whole path correct, correct transitions, transitions)."""
    ok_steps = sum(checker.legal(a, b) for a, b in itertools.pairwise(states))
    steps = len(states) - 1
    correct = states[0] == start and states[-1] == goal and ok_steps == steps
    return correct, ok_steps, steps


def sample_test_pairs(num_images: int, pairs: int, seed: int) -> np.ndarray:
    """Start/goal image indices, distinct within a pair, seeded."""
    rng = np.random.default_rng(seed)
    start = rng.integers(num_images, size=pairs)
    goal = (start + rng.integers(1, num_images, size=pairs)) % num_images
    return np.stack([start, goal], axis=1)


def shows_everything(task: Task, states: np.ndarray) -> np.ndarray:
    """Which state arrays an image shows whole (`Task.hidden`): a state with a hidden part
    looks like another, and no model can tell them apart."""
    return np.array([not task.hidden(task.array_to_state(s)) for s in states], dtype=bool)


def demonstrated_reach(
    train_states1: np.ndarray,
    train_states2: np.ndarray,
    a: np.ndarray,
    test_states: np.ndarray,
    pairs: np.ndarray,
) -> float:
    """% of the test pairs whose start and goal states the training data's action pairs chain
    together: the ceiling of % All for any roadmap made of demonstrated transitions (a state
    never demonstrated has no node; two states in different components have no path)."""
    n = len(train_states1)
    rows = np.concatenate([train_states1, train_states2]).reshape(2 * n, -1).astype(np.int64)
    seen, ids = np.unique(rows, axis=0, return_inverse=True)
    ids = ids.ravel()
    act = np.flatnonzero(a == 1)
    graph = coo_matrix((np.ones(len(act)), (ids[act], ids[n + act])), shape=(len(seen),) * 2)
    component = connected_components(graph, directed=False)[1]
    index = {row.tobytes(): c for row, c in zip(seen, component, strict=True)}
    test_rows = test_states.reshape(len(test_states), -1).astype(np.int64)
    test = [index.get(row.tobytes(), -1) for row in test_rows]
    joined = [test[i] != -1 and test[i] == test[j] for i, j in pairs]
    return 100.0 * float(np.mean(joined)) if len(pairs) else 0.0


def evaluate_plans(
    task_name: str,
    roadmap: Roadmap,
    labels: NodeLabels,
    z_test: np.ndarray,
    test_states: np.ndarray,
    pairs: np.ndarray,
    max_paths: int,
    node_reads: np.ndarray | None = None,
    calibration: Calibration | None = None,
) -> dict[str, Any]:
    """% All / Any / Trans over the pairs, plus decoded-image agreement when reads are given;
    with a calibration the ends are connected as the planner connects them (knowing.connect)."""
    task = get_task(task_name)
    checker = TransitionChecker(task)
    if roadmap.num_nodes == 0:  # e.g. a collapsed encoder: every latent in one pruned region
        return {
            "pairs": len(pairs),
            "all": 0.0,
            "any": 0.0,
            "trans": 0.0,
            "no_path": len(pairs),
            "truncated_at_max_paths": 0,
            "mean_path_nodes": 0.0,
            "detour_ratio": None,
        }
    node_states = [task.array_to_state(s) for s in labels.states]
    nearest = np.asarray(roadmap.nearest_node(z_test))
    n_all = n_any = ok_steps = steps = no_path = truncated = 0
    image_hits = image_total = 0
    lengths: list[int] = []
    detours: list[float] = []  # plan moves / fewest moves, where a plan is correct
    for i, j in pairs:
        start, goal = task.array_to_state(test_states[i]), task.array_to_state(test_states[j])
        ends = int(nearest[i]), int(nearest[j])
        if calibration is not None:
            ends = connect(roadmap, calibration, z_test[i], z_test[j], *ends)
        paths = roadmap.shortest_paths(*ends, max_paths=max_paths)
        if not paths:
            no_path += 1
            continue
        truncated += len(paths) == max_paths
        lengths.append(len(paths[0]))
        verdicts = [path_verdict(checker, [node_states[n] for n in p], start, goal) for p in paths]
        n_all += all(v[0] for v in verdicts)
        n_any += any(v[0] for v in verdicts)
        if any(v[0] for v in verdicts) and start != goal:
            detours.append((len(paths[0]) - 1) / optimal_moves(task, start, goal))
        ok_steps += sum(v[1] for v in verdicts)
        steps += sum(v[2] for v in verdicts)
        if node_reads is not None:
            for p in paths:
                hits = (node_reads[p] == labels.states[p]).reshape(len(p), -1).all(1)
                image_hits += int(hits.sum())
                image_total += len(p)
    n = len(pairs)
    result = {
        "pairs": n,
        "all": 100.0 * n_all / n,
        "any": 100.0 * n_any / n,
        "trans": 100.0 * ok_steps / steps if steps else 0.0,
        "no_path": no_path,
        "truncated_at_max_paths": truncated,
        "mean_path_nodes": float(np.mean(lengths)) if lengths else 0.0,
        "detour_ratio": float(np.mean(detours)) if detours else None,
    }
    if node_reads is not None:
        result["decoded_agreement"] = 100.0 * image_hits / image_total if image_total else 0.0
    return result


def evaluate_interpolation(
    task_name: str,
    reads: list[np.ndarray],
    test_states: np.ndarray,
    pairs: np.ndarray,
) -> dict[str, Any]:
    """The paper's baseline: images decoded along the straight line, read by the state reader.

    reads[k]: the state arrays read from the n_k decoded points of pair k.
    """
    task = get_task(task_name)
    checker = TransitionChecker(task)
    correct = ok_steps = steps = 0
    for (i, j), read in zip(pairs, reads, strict=True):
        states = []
        for array in read:
            try:
                states.append(task.array_to_state(array))
            except ValueError:
                states.append(None)  # not a valid state at all
        start, goal = task.array_to_state(test_states[i]), task.array_to_state(test_states[j])
        verdict = path_verdict(checker, states, start, goal)
        correct += verdict[0]
        ok_steps += verdict[1]
        steps += verdict[2]
    n = len(pairs)
    return {
        "pairs": n,
        "all": 100.0 * correct / n,
        "any": 100.0 * correct / n,
        "trans": 100.0 * ok_steps / steps if steps else 0.0,
    }


def class_distances(z: np.ndarray, classes: np.ndarray, metric: str) -> dict[str, Any]:
    """Paper VI-A1: intra-class distances to the class centroid and inter-centroid distances."""
    labels = np.unique(classes)
    centroids = np.stack([z[classes == c].mean(0) for c in labels])
    intra = [
        pair_distances(z[classes == c], centroids[k][None], metric) for k, c in enumerate(labels)
    ]
    inter = np.stack(
        [pair_distances(centroids, centroids[k][None], metric) for k in range(len(labels))]
    )
    np.fill_diagonal(inter, np.inf)
    score = np.array([inter[k].min() - intra[k].max() for k in range(len(labels))])
    finite = np.where(np.isinf(inter), np.nan, inter)
    return {
        "classes": len(labels),
        "mean_min_inter_minus_max_intra": float(score.mean()),
        "classes_separated": int((score >= 0).sum()),
        "intra_mean": np.array([d.mean() for d in intra]),
        "intra_std": np.array([d.std() for d in intra]),
        "inter_mean": np.nanmean(finite, axis=1),
        "inter_std": np.nanstd(finite, axis=1),
    }


def plot_class_distances(analyses: dict[str, dict[str, Any]], path: Path | str) -> None:
    """One panel per model, like the paper's figure: per class mean +- std, inter and intra."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(analyses), 1, figsize=(10, 2.6 * len(analyses)), squeeze=False)
    for ax, (name, a) in zip(axes[:, 0], analyses.items(), strict=True):
        x = np.arange(a["classes"])
        for key, colour, label in (
            ("inter", "tab:blue", "inter-class"),
            ("intra", "tab:orange", "intra-class"),
        ):
            ax.errorbar(
                x,
                a[f"{key}_mean"],
                yerr=a[f"{key}_std"],
                fmt="o",
                ms=2,
                elinewidth=0.4,
                color=colour,
                label=label,
            )
        ax.set_title(
            f"{name}: mean(min inter - max intra) = {a['mean_min_inter_minus_max_intra']:.2f}, "
            f"{a['classes_separated']}/{a['classes']} classes separated",
            fontsize=9,
        )
        ax.set_ylabel("distance")
        ax.legend(fontsize=7, loc="upper right")
    axes[-1, 0].set_xlabel("class (state index)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
