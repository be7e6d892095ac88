"""Dataset generation throughput: images per second written by `lsr data generate`.

Usage: python benchmarks/bench_datagen.py [--pairs 2000] [--size 64] [--workers 2]
Prints the end-to-end rate (spawning workers, physics, rendering, compression, writing) and,
for comparison, one process's bare render rate.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from services.sim.box_stacking.world import BoxStackingWorld
from services.sim.datagen import GenerateConfig, generate


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--pairs", type=int, default=2000)
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()

    with BoxStackingWorld(image_size=args.size) as world:
        world.reset(world.task.all_states()[0], np.random.default_rng(0))
        for _ in range(20):
            world.render()
        n = 500
        start = time.perf_counter()
        for _ in range(n):
            world.render()
        rate = n / (time.perf_counter() - start)
        print(f"render only, 1 process, {args.size}px: {rate:.0f} images/s")

    with tempfile.TemporaryDirectory() as tmp:
        cfg = GenerateConfig(pairs=args.pairs, image_size=args.size, workers=args.workers)
        result = generate(cfg, Path(tmp) / "data", progress=False)
    print(
        f"lsr data generate, {args.pairs} pairs, {args.size}px, {args.workers} workers: "
        f"{result['seconds']:.1f} s, {result['images_per_second']:.0f} images/s"
    )


if __name__ == "__main__":
    main()
