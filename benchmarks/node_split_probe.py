"""Which roadmap nodes hold two things: a probe for a node split, on a model's members.

Per node: whether nearly the same action from it (its pixel fields within --tol px, the task's
other fields equal) reaches two different nodes, and whether its images fall in two groups far
apart (2-means in the latent metric; gap = the closest pair across the groups over the node's
median nearest-neighbour distance). True states only name what a node holds (states, view
purity). Prints the nodes with the widest gaps.

    python benchmarks/node_split_probe.py MODEL [--tol 12] [--top 8]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from safetensors.numpy import load_file

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


def conflicting(moves: list[int], target: np.ndarray, actions: np.ndarray, tol: np.ndarray) -> bool:
    """Whether two of `moves` (tuple indices) do nearly the same action (each field within
    `tol`) and reach two nodes."""
    for k, i in enumerate(moves):
        for j in moves[k + 1 :]:
            near = bool((np.abs(actions[i] - actions[j]) <= tol).all())
            if target[i] != target[j] and near:
                return True
    return False


def probe(model: Path, tol: int) -> list[dict]:
    folder = model / "roadmap"
    task = get_task(json.loads((model / "recipe.json").read_text())["figures"]["task"])
    spec = task.spec.action
    fields = np.array([tol if name in spec.pixels else 0 for name in spec.names])
    members = load_file(str(folder / "members.safetensors"))
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
        d = np.abs(x[:, None] - x[None]).sum(-1)
        np.fill_diagonal(d, np.inf)
        spacing = float(np.median(d.min(1)))
        group = two_means(x, rng)
        smaller = int(min((group == 0).sum(), (group == 1).sum()))
        cross = float(d[group == 0][:, group == 1].min()) if smaller else 0.0
        moves = [int(t) for t in moved if node[2 * t] == n and target[t] >= 0]
        rows.append(
            {
                "node": n,
                "images": len(held),
                "states": len(np.unique(members["states"][held], axis=0)),
                "view_purity": labels.get(n, {}).get("purity", float("nan")),
                "conflict": conflicting(moves, target, actions, fields),
                "smaller_group": smaller,
                "gap": cross / spacing if spacing > 0 else float("inf"),
            }
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("model", type=Path)
    parser.add_argument("--tol", type=int, default=12, help="pixel fields of an action within this")
    parser.add_argument("--top", type=int, default=8)
    args = parser.parse_args()
    rows = probe(args.model, args.tol)
    for r in sorted(rows, key=lambda r: -r["gap"])[: args.top]:
        print(
            f"node {r['node']:3d} images {r['images']:4d} states {r['states']} view purity "
            f"{r['view_purity']:.2f} conflict {r['conflict']!s:5s} smaller group "
            f"{r['smaller_group']:4d} gap {r['gap']:.1f}"
        )
    print(f"nodes {len(rows)}, with conflicting actions {sum(r['conflict'] for r in rows)}")


if __name__ == "__main__":
    main()
