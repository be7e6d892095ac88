"""Regions of a VAE's training latents against epsilon: what the stable rule sees, with the truth.

For each epsilon on a geometric grid: the regions (phase 2 of Algorithm 1), those with at least 3
images, the share of no-action pairs inside one region, of action pairs inside one region
(the stable scan stops past 1%), and the purity (images in their region's most common state).
Prints the stable rule's choice first. The data must know its states.

Usage:
  python benchmarks/scan_epsilon.py --vae models/box_stacking/vae --data data/box1000
"""

from __future__ import annotations

import argparse

import numpy as np

from services.encoder.checkpoint import load_vae
from services.planner.members import Members
from services.planner.regions import connected_regions, pair_distances, stable_epsilon
from shared.dataset import load_dataset


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--vae", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--metric", default="l1", choices=["l1", "l2", "inf"])
    parser.add_argument("--steps", type=int, default=28)
    args = parser.parse_args()
    data = load_dataset(args.data)
    if data.spec.state is None:
        raise SystemExit(f"{args.data}: its images carry no states to judge regions by")
    points = Members.encode(load_vae(args.vae)[0], data).points.astype(np.float64)
    act = data.a.astype(bool)
    still, moved = np.flatnonzero(~act), np.flatnonzero(act)
    states = np.stack([data.state1, data.state2], 1).reshape(len(points), -1)
    truth = np.unique(states, axis=0, return_inverse=True)[1].ravel()
    epsilon, scan = stable_epsilon(points, still, moved, args.metric)
    print(f"{truth.max() + 1} states; stable epsilon {epsilon} (flat range {scan.get('range')})")
    d0 = pair_distances(points[2 * still], points[2 * still + 1], args.metric)
    d1 = pair_distances(points[2 * moved], points[2 * moved + 1], args.metric)
    for eps in np.geomspace(d0.mean() / 2, max(2 * d1.min(), 64 * d0.mean()), args.steps):
        labels = connected_regions(points, float(eps), args.metric)[0]
        sizes = np.bincount(labels)
        majority = sum(np.bincount(truth[labels == r]).max() for r in range(len(sizes)))
        print(
            f"epsilon {eps:8.3f}  regions {len(sizes):5d} (>= 3 images: {(sizes >= 3).sum():4d})"
            f"  no-action joined {np.mean(labels[2 * still] == labels[2 * still + 1]):.3f}"
            f"  action inside {np.mean(labels[2 * moved] == labels[2 * moved + 1]):.3f}"
            f"  purity {majority / len(labels):.3f}"
        )


if __name__ == "__main__":
    main()
