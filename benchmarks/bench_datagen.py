"""Dataset generation throughput: tuples and images per second written by `lsr data generate`.

Usage: python benchmarks/bench_datagen.py [--task box_stacking|cloth_folding] [--pairs 2000]
       [--size 64] [--workers 2]
Prints the end-to-end rate (spawning workers, physics, rendering, compression, writing), what
that rate means for 2000 tuples (the cloth-folding bar: at most 20 minutes at 64 px on 2 cores)
and, for comparison, one process's bare render rate.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from services.sim.datagen import GenerateConfig, generate
from services.sim.worlds import make_world
from shared.tasks import task_names


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--task", default="box_stacking", choices=task_names())
    parser.add_argument("--pairs", type=int, default=2000)
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()

    with make_world(args.task, args.size) as world:
        world.reset(world.task.all_states()[-1], np.random.default_rng(0))
        for _ in range(20):
            world.render()
        n = 500
        start = time.perf_counter()
        for _ in range(n):
            world.render()
        rate = n / (time.perf_counter() - start)
        print(f"render only, 1 process, {args.task}, {args.size}px: {rate:.0f} images/s")

    with tempfile.TemporaryDirectory() as tmp:
        cfg = GenerateConfig(
            task=args.task, pairs=args.pairs, image_size=args.size, workers=args.workers
        )
        result = generate(cfg, Path(tmp) / "data")
    per_tuple = result["seconds"] / args.pairs
    print(
        f"lsr data generate --task {args.task}, {args.pairs} pairs, {args.size}px, "
        f"{args.workers} workers: {result['seconds']:.1f} s, "
        f"{args.pairs / result['seconds']:.2f} tuples/s, {result['images_per_second']:.1f} images/s"
        f"; 2000 tuples would take {2000 * per_tuple / 60:.1f} min"
    )


if __name__ == "__main__":
    main()
