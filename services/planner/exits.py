"""Where a node's actions lead: one step of memory for nodes that stand for look-alike states.

A node may stand for several states that look alike: the T-shirt's side folded under its bottom
half hides whether its sleeve is folded. From such a node one action leads to different nodes
depending on the state hidden behind it, and the data show this: one action (`Task.same_action`)
leaving the node for several nodes. A path that came into the node from `a` came from the
state that this action leads back to `a` from, so a path that goes on by that action to another
node `c` takes a turn no chain of moves takes. Likewise a path that came in by an action and
leaves by the action the data show undoing it (from some node into this one by the first, and
back by the second) is back where it came from, not at another node: this holds where the
node that came in was split in two by the encoder (one state, two nodes, no image of one of
them seen after the undoing action). The roadmap records each node's exits
(`action_exits`, at build time) and its shortest paths avoid such turns (`forbidden_turns`,
`memory_paths`). A path may still start at such a node by any of its exits: a plan is valid
when it holds for some state showing the start's view (interface.md, "Views").

Only the last step is remembered: a task whose hidden part stays hidden over several steps
would need more. Nodes whose actions each lead to one node (every state its own view) forbid
nothing, and their paths are the roadmap's plain shortest paths.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import shortest_path

from shared.graphs import walks

Turns = dict[tuple[int, int], set[int]]  # (from a, at b) -> nodes c that b must not lead on to


def action_classes(
    a: np.ndarray, u: np.ndarray, same_action: Callable[[np.ndarray, np.ndarray], bool]
) -> np.ndarray:
    """(N,) int64: each tuple's action class, numbered in order of first use, -1 for no-action
    tuples; two actions share one when `same_action` says so (the same move, wherever made)."""
    firsts: list[np.ndarray] = []  # each class's first action
    classes = np.full(len(a), -1, np.int64)
    for i in np.flatnonzero(np.asarray(a) == 1).tolist():
        k = next((k for k, first in enumerate(firsts) if same_action(first, u[i])), None)
        if k is None:
            k = len(firsts)
            firsts.append(u[i])
        classes[i] = k
    return classes


def action_exits(
    point_node: np.ndarray,
    a: np.ndarray,
    u: np.ndarray,
    same_action: Callable[[np.ndarray, np.ndarray], bool],
) -> np.ndarray:
    """(X, 3) int64 rows (from node, to node, action class), sorted and unique: which action
    of the training tuples (`u[i]` where `a[i] == 1`) leads from each node to which
    (classes by `action_classes`)."""
    start, end = point_node[0::2], point_node[1::2]
    joins = (np.asarray(a) == 1) & (start >= 0) & (end >= 0) & (start != end)
    classes = action_classes(joins, u, same_action)
    rows = {(int(start[i]), int(end[i]), int(classes[i])) for i in np.flatnonzero(joins)}
    return np.array(sorted(rows), np.int64).reshape(-1, 3)


def forbidden_turns(exits: np.ndarray, group: np.ndarray) -> Turns:
    """The turns a -> b -> c (a != c) no chain of moves takes, between twin groups (`group`):
    every action leading from b to c also leads from b back to a, or undoes an action the data
    show leading from a into b (undoing: some node x goes into b by the one and b back to x by
    the other). The actions leading from b to a neighbour are those the data show, and the
    undoings of those the data show leading from it into b."""
    out: dict[int, dict[int, set[int]]] = {}  # b -> c -> the classes leading from b to c
    into: dict[int, dict[int, set[int]]] = {}  # b -> a -> the classes leading from a to b
    for start, end, k in exits.tolist():
        b, c = int(group[start]), int(group[end])
        if b != c:
            out.setdefault(b, {}).setdefault(c, set()).add(k)
            into.setdefault(c, {}).setdefault(b, set()).add(k)
    turns: Turns = {}
    for b in set(out) | set(into):
        to, came = out.get(b, {}), into.get(b, {})
        undoes = {(k, back) for x, ks in came.items() for k in ks for back in to.get(x, ())}
        near = set(to) | set(came)
        # the ways from b to each neighbour: seen, or the undoing of a way seen from it into b
        leaving = {
            c: to.get(c, set()) | {j for k, j in undoes if k in came.get(c, ())} for c in near
        }
        for a in near:
            back, entered = leaving[a], came.get(a, set())
            for c in near - {a}:
                onward = leaving[c]
                if not onward:
                    continue
                returns = onward <= back
                undone = bool(entered) and all(
                    any((k, j) in undoes for k in entered) for j in onward
                )
                if returns or undone:
                    turns.setdefault((a, b), set()).add(c)
    return turns


def memory_paths(
    indptr: np.ndarray,
    indices: np.ndarray,
    turns: Turns,
    s: int,
    t: int,
    banned: Iterable[tuple[int, int]],
    max_paths: int,
) -> list[list[int]]:
    """All shortest paths from s to t (s != t) over the adjacency (indptr, indices; sorted
    neighbours) that take no forbidden turn nor banned step, in lexicographic order of their
    node ids, at most max_paths; [] when none. Searched over the steps (u -> v) themselves,
    so that a step's successors can depend on where it came from."""
    rows = np.repeat(np.arange(len(indptr) - 1), np.diff(indptr))
    steps = len(indices)
    blocked = set(banned)
    ok = np.array([(int(u), int(v)) not in blocked for u, v in zip(rows, indices, strict=True)])
    source, sink = steps, steps + 1
    successors: list[list[int]] = [[] for _ in range(steps + 2)]
    for p in np.flatnonzero(ok).tolist():
        a, b = int(rows[p]), int(indices[p])
        if b == t:
            successors[p] = [sink]
            continue
        barred = turns.get((a, b), ())
        successors[p] = [
            q
            for q in range(indptr[b], indptr[b + 1])
            if ok[q] and int(indices[q]) != a and int(indices[q]) not in barred
        ]
    successors[source] = [q for q in range(indptr[s], indptr[s + 1]) if ok[q]]
    heads = [p for p, after in enumerate(successors) for _ in after]
    tails = [q for after in successors for q in after]
    graph = sparse.csr_matrix((np.ones(len(heads)), (heads, tails)), shape=(steps + 2,) * 2)
    from_s = shortest_path(graph, directed=True, unweighted=True, indices=source)
    to_t = shortest_path(graph.T.tocsr(), directed=True, unweighted=True, indices=sink)
    if not np.isfinite(from_s[sink]):
        return []

    def onward(p: int) -> list[int]:  # successors on a shortest path
        return [q for q in successors[p] if from_s[q] == from_s[p] + 1 and to_t[q] == to_t[p] - 1]

    found = walks(onward(source), onward, sink, max_paths)  # depth first: lexicographic
    return [[s, *(int(indices[p]) for p in taken)] for taken in found]
