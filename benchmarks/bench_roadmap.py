"""Roadmap build time (paper Algorithm 1) on box-stacking-like latents of growing size.

Usage: python benchmarks/bench_roadmap.py [--sizes 10000 100000 1000000] [--data vae reference]
       [--metric l1] [--seed 0]

Sizes count latent points (2 per tuple). Two kinds of synthetic latents, both with the 288 box-
stacking classes, 35% no-action pairs inside a class and 65% action pairs between neighbouring
classes:
- vae: classes spaced like a trained action-VAE (action pairs about 20 apart in L1, no-action
  pairs about 0.3), each class varying along its own 8-D patch (4 boxes x xy noise), and 0.1% of
  the latents thrown off their class (singleton regions, as in real encodings).
- reference: resampled from the reference release's latents (when present beside the project):
  its 288 region centres, each region's own covariance (scaled to the reference's no-action
  distances), its roadmap edges as the class graph. Its classes crowd closer than epsilon's
  triple, which makes phase 2 work harder.
Also times the build on the reference latents themselves. Prints the time of every phase.
"""

from __future__ import annotations

import argparse
import resource
import time
from pathlib import Path

import numpy as np

from services.planner.roadmap import Roadmap, RoadmapConfig, build_roadmap, pair_distances
from shared.tasks import get_task

REFERENCE = (
    Path(__file__).resolve().parents[1].parent
    / "shared/reference/data/lsr_v1_box_stacking_latents.npz"
)
DIM = 64
NO_ACTION = 0.35
OUTLIERS = 0.002  # of the tuples: their z1 leaves its class


def task_graph() -> tuple[int, np.ndarray]:
    """The 288 box-stacking configurations and their undirected transitions."""
    task = get_task("box_stacking")
    states = task.all_states()
    edges = set()
    for s in states:
        for _, t in task.neighbours(s):
            i, j = task.state_index(s), task.state_index(t)
            edges.add((min(i, j), max(i, j)))
    return len(states), np.array(sorted(edges), dtype=np.int64)


def tuples(
    n_points: int, n_classes: int, edges: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Class of z1 and z2 and the action flag of n_points / 2 tuples."""
    n = n_points // 2
    a = (rng.random(n) >= NO_ACTION).astype(np.int8)
    e = edges[rng.integers(len(edges), size=n)]
    flip = rng.random(n) < 0.5
    still = rng.integers(n_classes, size=n)
    c1 = np.where(a == 1, np.where(flip, e[:, 1], e[:, 0]), still)
    c2 = np.where(a == 1, np.where(flip, e[:, 0], e[:, 1]), still)
    return c1, c2, a


def sample(classes: np.ndarray, centres: np.ndarray, spread: list[np.ndarray], rng) -> np.ndarray:
    """Latents of the given classes: centre + spread[class] @ standard normal."""
    out = np.empty((len(classes), centres.shape[1]), dtype=np.float32)
    order = np.argsort(classes, kind="stable")
    bounds = np.searchsorted(classes[order], np.arange(len(centres) + 1))
    for k in range(len(centres)):
        rows = order[bounds[k] : bounds[k + 1]]
        noise = rng.standard_normal((len(rows), spread[k].shape[1]))
        out[rows] = centres[k] + noise @ spread[k].T
    return out


def vae_like(n_points: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    n_classes, edges = task_graph()
    # Coordinates N(0, 0.277^2): two centres are about 64 * 0.277 * 2 / sqrt(pi) = 20 apart in L1.
    centres = rng.normal(0.0, 0.277, size=(n_classes, DIM))
    # 8-D patches; 0.0016 per unit gives no-action pairs about 0.3 apart in L1.
    spread = [rng.normal(0.0, 0.0016, size=(DIM, 8)) for _ in range(n_classes)]
    c1, c2, a = tuples(n_points, n_classes, edges, rng)
    z1, z2 = sample(c1, centres, spread, rng), sample(c2, centres, spread, rng)
    off = rng.random(len(a)) < OUTLIERS
    z1[off] += rng.normal(0.0, 0.05, size=(int(off.sum()), DIM)).astype(np.float32)
    return z1, z2, a


def reference_like(n_points: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    data = np.load(REFERENCE)
    z1, z2, act = data["z1"], data["z2"], data["action"]
    ref = build_roadmap(z1, z2, act, RoadmapConfig(metric="l1", min_samples=3, eps_rule="paper"))
    points = np.empty((2 * len(z1), DIM), dtype=np.float64)
    points[0::2], points[1::2] = z1, z2
    centres, spread = [], []
    for k in range(ref.num_nodes):
        members = points[ref.point_node == k]
        centres.append(members.mean(0))
        # A Gaussian with the region's covariance: (members - mean).T @ w / sqrt(s - 1).
        spread.append((members - members.mean(0)).T / np.sqrt(max(1, len(members) - 1)))
    centres = np.array(centres)
    # Gaussians spread wider than the real (flatter) regions: match the no-action distances.
    c1, c2, a = tuples(20000, len(centres), ref.edges, rng)
    trial = sample(c1[a == 0], centres, spread, rng) - sample(c2[a == 0], centres, spread, rng)
    scale = ref.mu0 / float(np.abs(trial).sum(1).mean())
    spread = [s * scale for s in spread]
    c1, c2, a = tuples(n_points, len(centres), ref.edges, rng)
    z1, z2 = sample(c1, centres, spread, rng), sample(c2, centres, spread, rng)
    return z1, z2, a


def report(name: str, roadmap: Roadmap, seconds: float) -> None:
    s = roadmap.stats
    t = s["seconds"]
    p2 = s["phase2"]
    sub = ", ".join(f"{k} {v:.2f}" for k, v in p2.get("seconds", {}).items())
    print(
        f"{name}: {s['points']:,} points, total {seconds:.2f} s "
        f"(phase1 {t['phase1']:.2f}, epsilon {t['epsilon']:.2f}, phase2 {t['phase2']:.2f} "
        f"[{sub}], phase3 {t['phase3']:.2f}, pruning {t['pruning']:.2f})",
        flush=True,
    )
    print(
        f"    eps {roadmap.epsilon:.4f}; {s['regions_before_pruning']} regions, "
        f"{s['edges_before_pruning']} edges before pruning; {roadmap.num_nodes} nodes, "
        f"{len(roadmap.edges)} edges after; coarse balls {p2['coarse_balls']}, "
        f"stars {p2['stars']}, star pairs {p2['star_pairs']}, checks {p2['star_checks']}",
        flush=True,
    )


def timed_build(z1, z2, a, config: RoadmapConfig) -> tuple[Roadmap, float]:
    start = time.perf_counter()
    roadmap = build_roadmap(z1, z2, a, config)
    return roadmap, time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    parser.add_argument(
        "--data", nargs="+", choices=["vae", "reference"], default=["vae", "reference"]
    )
    parser.add_argument("--metric", choices=["l1", "l2", "inf"], default="l1")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--eps-rule",
        choices=["paper", "stable"],
        default="paper",
        help="paper: one phase 2 (Algorithm 1); stable: the default builder's scan of epsilon",
    )
    args = parser.parse_args()
    config = RoadmapConfig(metric=args.metric, min_samples=3, eps_rule=args.eps_rule)
    have_reference = REFERENCE.is_file()

    if have_reference:
        data = np.load(REFERENCE)
        runs = [timed_build(data["z1"], data["z2"], data["action"], config) for _ in range(3)]
        report("reference latents (best of 3)", *min(runs, key=lambda run: run[1]))
    else:
        print(f"reference latents not found at {REFERENCE}: skipping them")

    makers = {"vae": vae_like, "reference": reference_like}
    for kind in args.data:
        if kind == "reference" and not have_reference:
            print("reference-resampled latents need the reference latents: skipped")
            continue
        for size in args.sizes:
            z1, z2, a = makers[kind](size, args.seed)
            d0 = pair_distances(z1[a == 0], z2[a == 0], "l1")
            print(f"[{kind}] no-action L1 distance: mean {d0.mean():.3f}, max {d0.max():.3f}")
            roadmap, seconds = timed_build(z1, z2, a, config)
            report(f"{kind}-like", roadmap, seconds)
            del z1, z2, a, roadmap
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    print(f"peak memory of this process: {peak:.1f} GB")


if __name__ == "__main__":
    main()
