"""The paper's Table I, automatically: plan between unseen images and check every step.

A node stands for the view most of its training members show (`Task.view`: the state itself
where nothing hides). A path is correct when its first node looks like the start image, its last
like the goal image, and a chain of legal moves runs through states looking like its nodes
(interface.md, "Views"); `by_state` gives the stricter figures that judge the states themselves.
"""

from __future__ import annotations

import itertools
from collections import Counter
from collections.abc import Hashable, Sequence
from dataclasses import dataclass
from functools import cached_property
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


def label_nodes(
    point_node: np.ndarray, point_states: np.ndarray, num_nodes: int, task: Task | None = None
) -> NodeLabels:
    """Each node's label: the view most of its members show (`Task.view`; the state itself
    without a task), given as that view's most common state, and the share showing it.
    point_states: (2N, *state_shape) for the points numbered z1[0], z2[0], z1[1], ..."""
    shape = point_states.shape[1:]
    keys = [s.tobytes() for s in point_states]
    views: dict[bytes, Hashable] = {}  # state bytes -> its view

    def view(key: bytes) -> Hashable:
        if task is None:
            return key
        if key not in views:
            views[key] = task.view(task.array_to_state(_state_array(key, point_states)))
        return views[key]

    states = np.zeros((num_nodes, *shape), point_states.dtype)
    purity = np.zeros(num_nodes)
    members = np.zeros(num_nodes, np.int64)
    groups: dict[int, Counter] = {}
    for node, key in zip(point_node.tolist(), keys, strict=True):
        if node >= 0:
            groups.setdefault(node, Counter())[key] += 1
    for node, counter in groups.items():
        by_view: Counter = Counter()
        for key, count in counter.items():
            by_view[view(key)] += count
        shown, count = by_view.most_common(1)[0]
        key = max((k for k in counter if view(k) == shown), key=counter.__getitem__)
        states[node] = _state_array(key, point_states)
        members[node] = sum(counter.values())
        purity[node] = count / members[node]
    return NodeLabels(states, purity, members)


def _state_array(key: bytes, like: np.ndarray) -> np.ndarray:
    return np.frombuffer(key, like.dtype).reshape(like.shape[1:])


class TransitionChecker:
    """Judges steps, paths and actions by what a camera above shows (interface.md, "Views"):
    a path of views is right when some chain of legal moves runs through states showing them,
    an action when, applied from some state showing the first view, it gives one showing the
    second. `by_state` judges the states themselves: the stricter per-state figures. Where
    nothing hides (every state its own view) the two agree."""

    def __init__(self, task: Task, by_state: bool = False) -> None:
        self.task = task
        self.by_state = by_state
        self._next: dict[Any, set[Any]] = {}
        self._next_keys: dict[Hashable, set[Hashable]] = {}

    def key(self, state: Any) -> Hashable:
        return state if self.by_state else self.task.view(state)

    def same(self, s: Any, t: Any) -> bool:
        """`s` and `t` look alike (are equal, by state)."""
        return s is not None and t is not None and self.key(s) == self.key(t)

    @cached_property
    def _showing(self) -> dict[Hashable, tuple[Any, ...]]:
        groups: dict[Hashable, list[Any]] = {}
        for s in self.task.all_states() or ():
            groups.setdefault(self.key(s), []).append(s)
        return {k: tuple(v) for k, v in groups.items()}

    def showing(self, state: Any) -> tuple[Any, ...]:
        """Every state that looks like `state` (itself alone, by state)."""
        if state is None:
            return ()
        if self.by_state:
            return (state,)
        return self._showing.get(self.key(state), (state,))

    def _successors(self, state: Any) -> set[Any]:
        if state not in self._next:
            self._next[state] = {n for _, n in self.task.neighbours(state)}
        return self._next[state]

    def legal(self, s: Any, t: Any) -> bool:
        """One legal move leads from a state looking like `s` to one looking like `t`."""
        if s is None or t is None:  # an image that shows no valid state
            return False
        k = self.key(s)
        if k not in self._next_keys:
            self._next_keys[k] = {self.key(n) for u in self.showing(s) for n in self._successors(u)}
        return self.key(t) in self._next_keys[k]

    def chain(self, states: Sequence[Any]) -> bool:
        """Some chain of legal moves runs through states looking like `states`, in order."""
        if any(s is None for s in states):
            return False
        reach = set(self.showing(states[0]))
        for target in states[1:]:
            k = self.key(target)
            reach = {n for s in reach for n in self._successors(s) if self.key(n) == k}
            if not reach:
                return False
        return True

    def _after(self, reach: set[Any], action: Any, target: Any = None) -> set[Any]:
        """The states `action` legally leads to from those in `reach` (that look like
        `target`, when given)."""
        after = set()
        for s in reach:
            try:
                n = self.task.apply(s, action)
            except IllegalActionError:
                continue
            if target is None or self.same(n, target):
                after.add(n)
        return after

    def actions_lead(self, states: Sequence[Any], actions: Sequence[Any]) -> bool:
        """The actions, applied by the rules from some state looking like `states[0]`, pass
        through states looking like the rest (None, no action, never does)."""
        if any(s is None for s in states) or any(a is None for a in actions):
            return False
        reach = set(self.showing(states[0]))
        for action, target in zip(actions, states[1:], strict=True):
            reach = self._after(reach, action, target)
            if not reach:
                return False
        return True

    def reaches(self, start: Any, actions: Sequence[Any], goal: Any) -> bool:
        """A visual action plan's verdict (interface.md, "Views"): its actions, applied from
        some state looking like `start`, are legal moves that end in one looking like `goal`."""
        reach = set(self.showing(start))
        for action in actions:
            reach = self._after(reach, action)
        return any(self.same(s, goal) for s in reach)


def action_leads(checker: TransitionChecker, state: Any, action: Any, target: Any) -> bool:
    """The action, applied by the rules from `state` (or one looking like it), gives `target`
    (or one looking like it); None never does."""
    return checker.actions_lead([state, target], [action])


def path_verdict(
    checker: TransitionChecker, states: list[Any], start: Any, goal: Any
) -> tuple[bool, int, int]:
    """(whole path correct, correct transitions, transitions): correct when the path looks
    like the start at its first node and like the goal at its last, and a chain of legal moves
    runs through it."""
    ok_steps = sum(checker.legal(a, b) for a, b in itertools.pairwise(states))
    steps = len(states) - 1
    correct = (
        checker.same(states[0], start)
        and checker.same(states[-1], goal)
        and ok_steps == steps
        and checker.chain(states)
    )
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
    """% All / Any / Trans over the pairs judged by views, and under `by_state` by the nodes'
    states, plus decoded-image agreement when reads are given; with a calibration the ends are
    connected as the planner connects them (knowing.connect)."""
    task = get_task(task_name)
    judges = {"view": TransitionChecker(task), "state": TransitionChecker(task, by_state=True)}
    if roadmap.num_nodes == 0:  # e.g. a collapsed encoder: every latent in one pruned region
        return {
            "pairs": len(pairs),
            "all": 0.0,
            "any": 0.0,
            "trans": 0.0,
            "by_state": {"all": 0.0, "any": 0.0, "trans": 0.0},
            "no_path": len(pairs),
            "truncated_at_max_paths": 0,
            "mean_path_nodes": 0.0,
            "detour_ratio": None,
        }
    node_states = [task.array_to_state(s) for s in labels.states]
    nearest = np.asarray(roadmap.nearest_node(z_test))
    counts = {k: Counter() for k in judges}  # all, any, ok_steps, steps
    no_path = truncated = 0
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
        for key, judge in judges.items():
            verdicts = [
                path_verdict(judge, [node_states[n] for n in p], start, goal) for p in paths
            ]
            counts[key].update(
                all=all(v[0] for v in verdicts),
                any=any(v[0] for v in verdicts),
                ok_steps=sum(v[1] for v in verdicts),
                steps=sum(v[2] for v in verdicts),
            )
            if key == "view" and any(v[0] for v in verdicts) and not judge.same(start, goal):
                fewest = min(optimal_moves(task, s, goal) for s in judge.showing(start))
                detours.append((len(paths[0]) - 1) / fewest)
        if node_reads is not None:
            for p in paths:
                hits = (node_reads[p] == labels.states[p]).reshape(len(p), -1).all(1)
                image_hits += int(hits.sum())
                image_total += len(p)
    n = len(pairs)

    def table(c: Counter) -> dict[str, float]:
        return {
            "all": 100.0 * c["all"] / n,
            "any": 100.0 * c["any"] / n,
            "trans": 100.0 * c["ok_steps"] / c["steps"] if c["steps"] else 0.0,
        }

    result = {
        "pairs": n,
        **table(counts["view"]),
        "by_state": table(counts["state"]),
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
    """The paper's baseline: images decoded along the straight line, read by the state reader,
    judged by views as plans are.

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
