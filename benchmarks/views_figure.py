"""The views figure: what a camera above shows of a task, one registered camera image a view.

    python benchmarks/views_figure.py --task tshirt_folding --out docs/images/tshirt_views.png

Each tile is a state of the view reset from the settled-state library at the `camera` look,
its cell frame registered to the table frame as every model's input is, and labelled with the
folds it shows; a sleeve no camera above can see is written with a question mark. The T-shirt's
32 states give 25 views (`Task.view`, interface.md "Views").
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
from PIL import Image

from services.sim.workcell import Observer
from services.sim.worlds import make_world
from shared.images import contact_sheet


def label(task, state) -> str:
    """Short names of the folds seen, then '?' for each hidden part (the T-shirt's letters)."""
    folds, hidden = task.view(state)
    name = getattr(task, "short_name", lambda f: f)
    seen = "".join(name(f) for f in folds) or "flat"
    return seen + "".join(f" {name(h)}?" for h in hidden)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="tshirt_folding")
    parser.add_argument("--size", type=int, default=96)
    parser.add_argument("--look", default="camera")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("docs/images/tshirt_views.png"))
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    images, labels = [], []
    with make_world(args.task, args.size, appearance=args.look) as world:
        task = world.task
        observer = Observer(world)
        seen = set()
        for state in task.all_states():  # the first state of each view, in the task's order
            view = task.view(state)
            if view in seen:
                continue
            seen.add(view)
            world.reset(state, rng)
            images.append(observer.see())
            labels.append(label(task, state))
    sheet = contact_sheet(images, columns=7, labels=labels)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(sheet).save(args.out, optimize=True)
    print(f"wrote {args.out}: {len(images)} views")


if __name__ == "__main__":
    main()
