"""Which roadmap nodes hold two things: a probe for a node split, on a model's members.

Per node: whether nearly the same action from it (its pixel fields within --tol px, the task's
other fields equal) reaches two different nodes (conflicting pairs), and whether its images fall
in two groups far apart, asked two ways: 2-means in the latent metric (gap = the closest pair
across the groups over the node's median nearest-neighbour distance, in the roadmap's metric),
and the node's minimum spanning tree cut at its longest edge (cut = that edge over the tree's
median edge; agree = the share of conflicting pairs whose two starts the cut puts apart). True
states only name what a node holds (states, view purity). Prints the nodes first by --by.

    python benchmarks/node_split_probe.py MODEL [--tol 12] [--top 8] [--by gap|cut]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from safetensors.numpy import load_file
from scipy.sparse.csgraph import connected_components, minimum_spanning_tree

from services.planner.regions import pair_distances
from shared.tasks import get_task


def two_means(points: np.ndarray, rng: np.random.Generator, starts: int = 5) -> np.ndarray:
    """Labels 0/1 of the best of `starts` 2-means runs in L1."""
    best: tuple[float, np.ndarray] | None = None
    for _ in range(starts):
        centres = points[rng.choice(len(points), 2, replace=False)]
        for _ in range(30):
            labels = np.abs(points[:, None] - centres[None]).sum(-1).argmin(1)
            if labels.min() == labels.max():
                break
            centres = np.stack([points[labels == k].mean(0) for k in (0, 1)])
        cost = float(np.abs(points - centres[labels]).sum())
        if best is None or cost < best[0]:
            best = (cost, labels)
    assert best is not None
    return best[1]


def conflicting(
    moves: list[int], target: np.ndarray, actions: np.ndarray, tol: np.ndarray
) -> list[tuple[int, int]]:
    """The pairs of `moves` (tuple indices) that do nearly the same action (each field within
    `tol`) and reach two nodes."""
    return [
        (i, j)
        for k, i in enumerate(moves)
        for j in moves[k + 1 :]
        if target[i] != target[j] and bool((np.abs(actions[i] - actions[j]) <= tol).all())
    ]


def tree_cut(distances: np.ndarray) -> tuple[np.ndarray, float]:
    """The two groups the minimum spanning tree leaves when cut at its longest edge, and that
    edge over the tree's median edge."""
    tree = minimum_spanning_tree(distances + 1e-12).toarray()
    edges = np.argwhere(tree > 0)
    weights = tree[tree > 0]
    longest = int(np.argmax(weights))
    tree[tuple(edges[longest])] = 0
    _, group = connected_components(tree, directed=False)
    return group, float(weights[longest] / np.median(weights))


def read_model(model: Path, tol: int) -> tuple[np.ndarray, str, dict[str, np.ndarray]]:
    """(each action field's tolerance: `tol` for pixels, 0 for the task's other fields; the
    roadmap's metric; the members) of a built model."""
    spec = get_task(json.loads((model / "recipe.json").read_text())["figures"]["task"]).spec.action
    fields = np.array([tol if name in spec.pixels else 0 for name in spec.names])
    metric = json.loads((model / "roadmap" / "roadmap.json").read_text())["config"]["metric"]
    return fields, metric, load_file(str(model / "roadmap" / "members.safetensors"))


def all_pairs(points: np.ndarray, metric: str) -> np.ndarray:
    """The distance matrix of `points`."""
    return pair_distances(points[:, None], points[None], metric)


def probe(model: Path, tol: int) -> list[dict]:
    folder = model / "roadmap"
    fields, metric, members = read_model(model, tol)
    roadmap = load_file(str(folder / "roadmap.safetensors"))
    labels = {d["node"]: d for d in json.loads((folder / "labels.json").read_text())}
    node, points = roadmap["point_node"], members["points"]
    actions = members["actions"].astype(int)
    moved = np.flatnonzero(members["a"] == 1)
    target = node[2 * np.arange(len(members["a"])) + 1]
    rng = np.random.default_rng(0)
    rows = []
    for n in range(len(roadmap["nodes"])):
        held = np.flatnonzero(node == n)
        if len(held) < 4:
            continue
        x = points[held]
        d = all_pairs(x, metric)
        cut, ratio = tree_cut(d)
        np.fill_diagonal(d, np.inf)
        spacing = float(np.median(d.min(1)))
        group = two_means(x, rng)
        smaller = int(min((group == 0).sum(), (group == 1).sum()))
        cross = float(d[group == 0][:, group == 1].min()) if smaller else 0.0
        moves = [int(t) for t in moved if node[2 * t] == n and target[t] >= 0]
        pairs = conflicting(moves, target, actions, fields)
        side = dict(zip(held.tolist(), cut.tolist(), strict=True))
        rows.append(
            {
                "node": n,
                "images": len(held),
                "states": len(np.unique(members["states"][held], axis=0)),
                "view_purity": labels.get(n, {}).get("purity", float("nan")),
                "conflicting": len(pairs),
                "smaller_group": smaller,
                "gap": cross / spacing if spacing > 0 else float("inf"),
                "cut": ratio,
                "cut_smaller": int(np.bincount(cut).min()),
                "agree": float(np.mean([side[2 * i] != side[2 * j] for i, j in pairs]))
                if pairs
                else 0.0,
            }
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("model", type=Path)
    parser.add_argument("--tol", type=int, default=12, help="pixel fields of an action within this")
    parser.add_argument("--top", type=int, default=8)
    parser.add_argument("--by", choices=("gap", "cut"), default="gap", help="cut: agree x cut")
    args = parser.parse_args()
    rows = probe(args.model, args.tol)
    order = (lambda r: -r["gap"]) if args.by == "gap" else (lambda r: -r["agree"] * r["cut"])
    for r in sorted(rows, key=order)[: args.top]:
        print(
            f"node {r['node']:3d} images {r['images']:4d} states {r['states']} view purity "
            f"{r['view_purity']:.2f} conflicting {r['conflicting']:4d} | 2-means smaller "
            f"{r['smaller_group']:4d} gap {r['gap']:5.1f} | tree cut smaller "
            f"{r['cut_smaller']:4d} cut {r['cut']:5.1f} agree {r['agree']:.2f}"
        )
    conflicted = sum(r["conflicting"] > 0 for r in rows)
    print(f"nodes {len(rows)}, with conflicting actions {conflicted}")


if __name__ == "__main__":
    main()
