"""`lsr build-roadmap`, `lsr calibrate`, `lsr roadmap ...` and `lsr explore`: a trained VAE's
roadmap, what it knows, and how it grows from experience."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def cmd_build_roadmap(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from services.encoder.checkpoint import read_vae_config
    from services.planner.build import build_from_dataset, default_metric
    from services.recipe import Choices
    from shared.dataset import read_manifest

    metric = args.metric or default_metric(read_vae_config(args.vae))
    # As lsr train model chooses: flags, the dataset's task.json settings, what was measured
    # for its task, then the defaults (the stable cut, w 1, pruning automatic).
    manifest = read_manifest(args.data)
    choices = Choices(manifest["task"], manifest.get("settings") or {})
    chosen = choices.roadmap(metric, args.eps_rule, args.w_eps, args.min_samples)
    config = replace(chosen, matching=args.matching, min_edge_weight=args.min_edge_weight)
    for line in choices.why:
        print(f"  {line}", file=sys.stderr)
    summary = build_from_dataset(args.vae, args.data, config, args.out)
    print(json.dumps(summary))
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    from services.planner.build import calibrate_model

    print(json.dumps(calibrate_model(args.model, args.data)))
    return 0


def cmd_grow(args: argparse.Namespace) -> int:
    from services.planner.grow import grow_model

    print(json.dumps(grow_model(args.model, args.experience, args.data)))
    return 0


def cmd_versions(args: argparse.Namespace) -> int:
    from services.planner import versions

    if args.use:
        with versions.growing(args.model):  # not while a growth publishes or a prune deletes
            versions.make_current(args.model, args.use)
    deleted = versions.prune(args.model, args.keep) if args.keep is not None else []
    current = versions.current_version(args.model)
    listing = {"current": current, "versions": versions.versions(args.model)}
    print(json.dumps(listing | ({"deleted": deleted} if args.keep is not None else {})))
    return 0


def cmd_explore(args: argparse.Namespace) -> int:
    from services.cli.common import single_thread_torch
    from services.sim.explore import ExploreConfig, explore

    single_thread_torch()
    cfg = ExploreConfig(
        actions=args.actions,
        seed=args.seed,
        grow_every=args.grow_every,
        chain=args.chain,
        looks=args.looks,
    )
    experience = args.experience or args.model / "experience" / "explore"
    print(json.dumps(explore(args.model, cfg, experience, args.data)))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    roadmap = sub.add_parser("build-roadmap", help="build the Latent Space Roadmap of a VAE")
    roadmap.add_argument("--vae", required=True, type=Path)
    roadmap.add_argument("--data", required=True, type=Path, help="training dataset folder")
    roadmap.add_argument(
        "--eps-rule",
        choices=["stable", "paper"],
        help="stable: the cut that keeps the regions unchanged longest; paper: Algorithm 1's "
        "mu0 + w_eps sigma0 (default: task.json's settings, else what was measured for the "
        "task, else stable)",
    )
    roadmap.add_argument(
        "--w-eps",
        type=float,
        help="w of the paper's rule (and its fallback); default: task.json's settings, else "
        "what was measured for the task, else 1",
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
    roadmap.add_argument(
        "--matching",
        default="whitened",
        choices=["whitened", "metric"],
        help="how an image finds its node: whitened by the spread of images within nodes "
        "(default; the metric where too few images share a node), or in the metric, as the paper",
    )
    roadmap.add_argument(
        "--min-edge-weight",
        type=int,
        default=1,
        help="drop edges fewer action pairs support (default 1: keep every edge, as the paper)",
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

    group = sub.add_parser("roadmap", help="a model's roadmap versions, and growing them")
    verbs = group.add_subparsers(dest="sub", required=True)
    grow = verbs.add_parser(
        "grow",
        help="grow the model's current roadmap by experience (the VAE fixed) into a new version",
    )
    grow.add_argument("--model", required=True, type=Path, help="vae/ and roadmap/ folder")
    grow.add_argument(
        "--experience", required=True, type=Path, nargs="+", help="experience folder(s)"
    )
    grow.add_argument(
        "--data",
        type=Path,
        help="the model's training data, for a roadmap built before members were kept "
        "(default: the path the VAE recorded)",
    )
    grow.set_defaults(handler=cmd_grow)
    listing = verbs.add_parser("versions", help="the versions a model keeps, and which plans")
    listing.add_argument("--model", required=True, type=Path)
    listing.add_argument("--use", help="make this version current (v1, v2, ...): a roll-back")
    listing.add_argument(
        "--keep",
        type=int,
        help="delete grown versions but the KEEP newest (v1, the current and the newest stay)",
    )
    listing.set_defaults(handler=cmd_versions)

    explore = sub.add_parser(
        "explore",
        help="spend an action budget in the simulator where the roadmap is thin, and grow it",
    )
    explore.add_argument("--model", required=True, type=Path)
    explore.add_argument("--actions", required=True, type=int, help="actions to try")
    explore.add_argument(
        "--experience", type=Path, help="where to record (default: MODEL/experience/explore)"
    )
    explore.add_argument("--seed", type=int, default=0)
    explore.add_argument("--grow-every", type=int, default=100)
    explore.add_argument("--chain", type=int, default=3, help="actions in a row from one start")
    explore.add_argument(
        "--looks",
        type=int,
        default=0,
        help="looks again after each executed action, recorded as no-action pairs (new states "
        "get enough images to become nodes in one visit)",
    )
    explore.add_argument("--data", type=Path, help="as for lsr roadmap grow")
    explore.set_defaults(handler=cmd_explore)
