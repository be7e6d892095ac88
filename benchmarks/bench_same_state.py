"""Does the same-state radius separate states in this latent space? (issue 22)

Growth joins an image to a node only within the same-state radius of an image there
(`services.planner.grow.same_state_radius`, from the training pairs alone). This prints, for a
model whose roadmap has grown from experience with re-observations (`lsr explore --looks N`),
the radius beside the distances it stands for: the training no-action pairs it was made from,
the experience's no-action pairs (fresh looks at one state) and the action pairs (two states
one move apart). One JSON line.

    python benchmarks/bench_same_state.py --model runs/experience/box250l/model
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from services.planner.grow import same_state_radius
from services.planner.members import Members
from services.planner.regions import pair_distances
from services.planner.roadmap import Roadmap
from services.planner.versions import roadmap_dir


def quantiles(values: np.ndarray) -> dict[str, float] | None:
    if not len(values):
        return None
    q = np.quantile(values, [0.01, 0.1, 0.5, 0.9, 0.99])
    return dict(zip(("q01", "q10", "q50", "q90", "q99"), np.round(q, 3).tolist(), strict=True))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, required=True)
    args = parser.parse_args()
    folder = roadmap_dir(args.model)
    members, roadmap = Members.load(folder), Roadmap.load(folder)
    metric = roadmap.config.metric
    radius = same_state_radius(members, metric, roadmap.epsilon)
    gaps = pair_distances(members.points[0::2], members.points[1::2], metric)
    experience, moved = members.experience.astype(bool), members.a == 1
    looks = gaps[experience & ~moved]
    print(
        json.dumps(
            {
                "model": str(args.model),
                "radius": round(radius, 3),
                "training_no_action": quantiles(gaps[~experience & ~moved]),
                "experience_no_action": quantiles(looks),
                "action": quantiles(gaps[moved]),
                "looks_within_radius": round(float((looks <= radius).mean()), 3)
                if len(looks)
                else None,
            }
        )
    )


if __name__ == "__main__":
    main()
