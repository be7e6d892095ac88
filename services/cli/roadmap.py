"""`lsr build-roadmap` and `lsr calibrate`: a trained VAE's roadmap and what it knows."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def cmd_build_roadmap(args: argparse.Namespace) -> int:
    from services.cli.common import dataset_setting
    from services.encoder.checkpoint import read_vae_config
    from services.planner.build import build_from_dataset, default_metric
    from services.planner.roadmap import RoadmapConfig

    metric = args.metric or default_metric(read_vae_config(args.vae))
    # Flags first, then the dataset's task.json settings, then the defaults (w 1; pruning
    # automatic, as RoadmapConfig's min_samples None).
    w_eps = args.w_eps if args.w_eps is not None else dataset_setting(args.data, "w_eps")
    min_samples = args.min_samples
    if min_samples is None:
        min_samples = dataset_setting(args.data, "min_samples")
    config = RoadmapConfig(
        metric=metric,
        w_eps=1.0 if w_eps is None else float(w_eps),
        min_samples=None if min_samples is None else int(min_samples),
        eps_rule=args.eps_rule,
    )
    summary = build_from_dataset(args.vae, args.data, config, args.out)
    print(json.dumps(summary))
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    from services.planner.build import calibrate_model

    print(json.dumps(calibrate_model(args.model, args.data)))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    roadmap = sub.add_parser("build-roadmap", help="build the Latent Space Roadmap of a VAE")
    roadmap.add_argument("--vae", required=True, type=Path)
    roadmap.add_argument("--data", required=True, type=Path, help="training dataset folder")
    roadmap.add_argument(
        "--eps-rule",
        default="stable",
        choices=["stable", "paper"],
        help="stable: the cut that keeps the regions unchanged longest (default); "
        "paper: Algorithm 1's mu0 + w_eps sigma0",
    )
    roadmap.add_argument(
        "--w-eps",
        type=float,
        help="w of the paper's rule (and its fallback); default: task.json's settings, else 1",
    )
    roadmap.add_argument(
        "--min-samples",
        type=int,
        help="prune regions with fewer members (default: the dataset's task.json settings, "
        "else a tenth of the typical region, >= 1)",
    )
    roadmap.add_argument(
        "--metric",
        choices=["l1", "l2", "inf"],
        help="default: the VAE's training metric (l1 for the baseline)",
    )
    roadmap.add_argument("--out", required=True, type=Path)
    roadmap.set_defaults(handler=cmd_build_roadmap)

    calibrate = sub.add_parser(
        "calibrate",
        help="set how far from the roadmap an image may lie and still be known (build-roadmap "
        "does it; this is for models built before)",
    )
    calibrate.add_argument("--model", required=True, type=Path, help="vae/ and roadmap/ folder")
    calibrate.add_argument("--data", required=True, type=Path, help="the model's training data")
    calibrate.set_defaults(handler=cmd_calibrate)
