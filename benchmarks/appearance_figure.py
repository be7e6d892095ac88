"""The appearance figure: one state of each task under clean, camera and shifted.

    python benchmarks/appearance_figure.py --out docs/images/appearance_levels.png

Each row is one task's world at one seeded state; camera and shifted show two episodes each
(two resets of the same state, each drawing its own look), so the figure shows the spread.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
from PIL import Image

from services.sim.worlds import make_world
from shared.appearance import CLEAN
from shared.images import contact_sheet

COLUMNS = [(CLEAN, 0), ("camera", 1), ("camera", 2), ("shifted", 1), ("shifted", 2)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=["box_stacking", "cloth_folding"])
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path("docs/images/appearance_levels.png"))
    args = parser.parse_args()
    images, labels = [], []
    for name in args.tasks:
        with make_world(name, args.size, appearance=CLEAN) as world:
            state = world.task.sample_state(np.random.default_rng(args.seed))
            for level, episode in COLUMNS:
                world.use(level)  # type: ignore[attr-defined]
                world.reset(state, np.random.default_rng([args.seed, episode]))
                images.append(world.render())
                labels.append(f"{level} {episode}" if level != CLEAN else f"{name} {level}")
    sheet = contact_sheet(images, columns=len(COLUMNS), labels=labels)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(sheet).save(args.out, optimize=True)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
