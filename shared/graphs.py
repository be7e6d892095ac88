"""Graph helpers that the planner and the viewer both need about a roadmap's nodes."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components


def twin_groups(nodes: int, twins: np.ndarray) -> np.ndarray:
    """Each of `nodes` nodes' twin group, named by its smallest node id (its own id when it has
    no twin): the nodes that no-action pairs showed to be one state, through chains of twins."""
    group = np.arange(nodes)
    if not len(twins):
        return group
    label = node_components(nodes, twins)
    first = np.full(label.max() + 1, nodes)
    np.minimum.at(first, label, group)
    return first[label]


def node_components(nodes: int, edges: np.ndarray) -> np.ndarray:
    """The connected component of each of `nodes` nodes that `edges` (E, 2) join."""
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(nodes, nodes))
    return connected_components(graph, directed=False)[1]


def walks(
    first: list[int], onward: Callable[[int], list[int]], end: int, limit: int
) -> list[list[int]]:
    """Every walk from one of `first` along `onward` until `end` (left out), depth first in the
    order `onward` gives, at most `limit`: the enumeration behind a roadmap's shortest paths."""
    found: list[list[int]] = []
    path: list[int] = []
    stack = [iter(first)]
    while stack:
        v = next(stack[-1], None)
        if v is None:
            stack.pop()
            if path:
                path.pop()
        elif v == end:
            found.append(list(path))
            if len(found) == limit:
                break
        else:
            path.append(v)
            stack.append(iter(onward(v)))
    return found
