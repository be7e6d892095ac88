"""`lsr data`: datasets."""

from __future__ import annotations

import argparse
from pathlib import Path

from shared.tasks import task_names


def cmd_data_generate(args: argparse.Namespace) -> int:
    from services.sim.datagen import GenerateConfig, generate

    cfg = GenerateConfig(
        task=args.task,
        pairs=args.pairs,
        seed=args.seed,
        image_size=args.size,
        action_fraction=args.action_fraction,
        workers=args.workers,
        episode_length=args.episode_length,
        starts=args.starts,
    )
    result = generate(cfg, args.out, overwrite=args.overwrite)
    counts = result["counts"]
    print(
        f"wrote {counts['tuples']} tuples ({counts['action_pairs']} action, "
        f"{counts['no_action_pairs']} no-action) to {args.out} in {result['seconds']:.1f} s "
        f"({result['images_per_second']:.0f} images/s)"
    )
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    data = sub.add_parser("data", help="datasets").add_subparsers(dest="sub", required=True)
    gen = data.add_parser("generate", help="render a dataset of action and no-action pairs")
    gen.add_argument("--task", default="box_stacking", choices=task_names())
    gen.add_argument("--pairs", type=int, default=5000, help="number of tuples")
    gen.add_argument("--seed", type=int, default=0)
    gen.add_argument("--size", type=int, default=64, help="image size in pixels (square)")
    gen.add_argument("--action-fraction", type=float, default=0.65)
    gen.add_argument("--workers", type=int, default=2, help="rendering processes")
    gen.add_argument(
        "--episode-length",
        type=int,
        default=None,
        help="tuples walked from one reset (default: the world's, 1 box stacking, 10 cloth)",
    )
    gen.add_argument(
        "--starts",
        default="balanced",
        choices=["balanced", "random"],
        help="episode start states: every state in turn (default) or drawn independently",
    )
    gen.add_argument("--out", required=True, type=Path)
    gen.add_argument("--overwrite", action="store_true", help="replace an existing folder")
    gen.set_defaults(handler=cmd_data_generate)
