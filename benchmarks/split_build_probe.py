"""What a node split would buy: a model's roadmap built again with one, to evaluate.

The split (not in the product; measured here first): after Algorithm 1's phase 2, a region whose
moves include nearly the same action (pixel fields within --tol px, the task's other fields
equal) reaching two regions is cut at the longest edge of its minimum spanning tree (in the
roadmap's metric) when that cut puts the starts of every such pair apart, the edge is at least
--cut times the tree's median edge and each side holds at least --side images; the smaller
side becomes a region of its own. Everything else is `lsr build-roadmap` with its defaults.
Copies MODEL to OUT with the new roadmap and prints the splits; then `lsr eval vfm --model OUT
--test T`.

    python benchmarks/split_build_probe.py --model M --data TRAIN --out OUT
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import numpy as np
from node_split_probe import all_pairs, conflicting, read_model, tree_cut

import services.planner.roadmap as roadmap_module
from services.cli import main as lsr


def split(
    labels: np.ndarray,
    points: np.ndarray,
    moved: np.ndarray,
    actions: np.ndarray,
    tol: np.ndarray,
    metric: str,
    cut: float,
    side: int,
) -> tuple[np.ndarray, list[dict]]:
    """`labels` with the regions split as the module docstring says, and what was split."""
    labels, done = labels.copy(), []
    for region in range(int(labels.max()) + 1):
        held = np.flatnonzero(labels == region)
        starts = [int(t) for t in moved if labels[2 * t] == region]
        pairs = conflicting(starts, labels[1::2], actions, tol)
        if not pairs or len(held) < 2 * side:
            continue
        x = points[held]
        group, ratio = tree_cut(all_pairs(x, metric))
        where = dict(zip(held.tolist(), group.tolist(), strict=True))
        apart = all(where[2 * i] != where[2 * j] for i, j in pairs)
        sizes = np.bincount(group)
        if apart and ratio >= cut and sizes.min() >= side:
            labels[held[group == int(np.argmin(sizes))]] = labels.max() + 1
            done.append(
                {"region": region, "images": len(held), "split_off": int(sizes.min()),
                 "cut": round(ratio, 1), "pairs": len(pairs)}
            )  # fmt: skip
    return labels, done


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--model", type=Path, required=True, help="a model built on --data")
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--tol", type=int, default=12)
    parser.add_argument("--cut", type=float, default=3.0)
    parser.add_argument("--side", type=int, default=3)
    args = parser.parse_args()
    tol, _, members = read_model(args.model, args.tol)  # the cut takes the build's metric
    moved = np.flatnonzero(members["a"] == 1)
    actions = members["actions"].astype(int)
    found: list[dict] = []
    regions = roadmap_module.connected_regions

    def with_split(points: np.ndarray, epsilon: float, metric: str):
        labels, info = regions(points, epsilon, metric)
        if len(labels) != 2 * len(members["a"]):
            sys.exit(f"{args.model} was not built on {args.data}: its members differ in number")
        labels, done = split(
            labels, np.asarray(points), moved, actions, tol, metric, args.cut, args.side
        )
        found.extend(done)
        return labels, info

    roadmap_module.connected_regions = with_split  # phase 2 of build_roadmap only
    shutil.rmtree(args.out, ignore_errors=True)
    shutil.copytree(args.model, args.out, ignore=shutil.ignore_patterns("roadmap"))
    rc = lsr(["build-roadmap", "--vae", str(args.out / "vae"), "--data", str(args.data),
              "--out", str(args.out / "roadmap")])  # fmt: skip
    print(f"splits: {found}")
    sys.exit(rc)


if __name__ == "__main__":
    main()
