"""Grow a model's roadmap from experience, the VAE fixed: a new version, the old one kept.

    LSR_EXPERIENCE_DIR=runs/experience lsr up     # robots report what they did (lsr robot
                                                  # --report, POST /experience)
    python examples/grow_roadmap.py --model runs/box1000 --experience runs/experience/box_stacking

Experience folders are datasets that grow: the gateway records robots' reports, the closed loop
(`lsr eval system --experience DIR`) and `lsr explore` record the simulator's. Growth takes only
the tuples the roadmap has not grown from, writes `roadmap/versions/vK/` and makes it current;
running planners take it within a second. A model built before roadmaps kept their members
needs its training data once (`--data`). Roll back with `lsr roadmap versions --use v1`.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from services.planner.grow import grow_model
from services.planner.versions import current_version, versions


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, required=True, help="a folder with vae/, roadmap/")
    parser.add_argument("--experience", type=Path, nargs="+", required=True)
    parser.add_argument("--data", type=Path, help="the training data, for an older model")
    args = parser.parse_args()

    report = grow_model(args.model, args.experience, args.data)
    kept = ("version", "tuples", "new_nodes", "new_edges", "held_for_review", "components")
    print(json.dumps({k: report[k] for k in kept if k in report}))
    print(f"versions {versions(args.model)}, current {current_version(args.model)}")


if __name__ == "__main__":
    main()
