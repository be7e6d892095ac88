"""`lsr data`: datasets."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from shared.appearance import LEVELS, levels_help
from shared.tasks import DEFAULT_TASK, get_task, task_names


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
        appearance=args.appearance,
        look_pairs=args.look_pairs,
    )
    result = generate(cfg, args.out, overwrite=args.overwrite)
    counts = result["counts"]
    print(
        f"wrote {counts['tuples']} tuples ({counts['action_pairs']} action, "
        f"{counts['no_action_pairs']} no-action, {counts['look_pairs']} of them across looks) "
        f"to {args.out} in {result['seconds']:.1f} s ({result['images_per_second']:.0f} images/s)"
    )
    registration = result["registration"]
    if registration is not None:
        print(
            f"registered {registration['frames']} frames to the table frame (corner error "
            f"p50 {registration['error_px_p50']} px, max {registration['error_px_max']} px); "
            f"{registration['refused']} frames without their markers were looked at again"
        )
    return 0


def cmd_data_import(args: argparse.Namespace) -> int:
    from services.data.importer import ImportConfig, import_dataset

    cfg = ImportConfig(
        source=args.source,
        out=args.out,
        name=args.name,
        test_fraction=args.test_fraction,
        seed=args.seed,
        overwrite=args.overwrite,
    )
    result = import_dataset(cfg)
    if result["registered"]:
        print(
            f"registered {result['registered']} of {result['images']} images to the table "
            f"frame with task.json's markers, {result['image_size']} px; sizes found: "
            f"{result['image_sizes']}"
        )
    if result["resized"]:
        print(
            f"resized {result['resized']} of {result['images']} images to "
            f"{result['image_size']} px; {result['cropped']} not square were centre-cropped "
            f"first (aspect kept); sizes found: {result['image_sizes']}"
        )
    if result["own_episodes"]:
        print("rows without an episode are each their own episode for the split")
    for split, counts in result["splits"].items():
        print(
            f"{split}: {counts['tuples']} tuples ({counts['action_pairs']} action), "
            f"{counts['episodes']} episodes -> {Path(args.out) / split}"
        )
    print(json.dumps(result))
    return 0


def cmd_data_export(args: argparse.Namespace) -> int:
    from services.data.exporter import export_dataset

    result = export_dataset(args.data, args.out, overwrite=args.overwrite)
    if result["states_dropped"]:
        print("states are not exported: the import format has none")
    print(json.dumps(result))
    return 0


def cmd_data_merge(args: argparse.Namespace) -> int:
    from services.data.merge import merge_datasets

    result = merge_datasets(args.data, args.out, overwrite=args.overwrite)
    print(
        f"wrote {result['tuples']} tuples ({result['action_pairs']} action pairs) from "
        f"{result['sources']} datasets to {args.out}; train on it with "
        f"lsr train model --data {args.out}"
    )
    print(json.dumps(result))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    data = sub.add_parser("data", help="datasets").add_subparsers(dest="sub", required=True)
    gen = data.add_parser("generate", help="render a dataset of action and no-action pairs")
    gen.add_argument("--task", default=DEFAULT_TASK, choices=task_names())
    gen.add_argument("--pairs", type=int, default=5000, help="number of tuples")
    gen.add_argument("--seed", type=int, default=0)
    gen.add_argument("--size", type=int, default=64, help="image size in pixels (square)")
    gen.add_argument("--action-fraction", type=float, default=0.65)
    gen.add_argument("--workers", type=int, default=2, help="rendering processes")
    gen.add_argument(
        "--episode-length",
        type=int,
        default=None,
        help="tuples walked from one reset (default: the world's, 1 box stacking, 10 cloth and "
        "T-shirt, shortened where fewer would not go round every state twice)",
    )
    gen.add_argument(
        "--starts",
        default="balanced",
        choices=["balanced", "random"],
        help="episode start states: every state in turn (default) or drawn independently",
    )
    gen.add_argument(
        "--appearance",
        default=None,
        choices=LEVELS,
        help="how the images look, recorded in the manifest; default: the task's own ("
        + ", ".join(f"{t}: {get_task(t).default_look}" for t in task_names())
        + f") ({levels_help()})",
    )
    gen.add_argument(
        "--look-pairs",
        type=float,
        default=None,
        help="share of no-action pairs whose second image is the same state under a fresh "
        "look (lights, table, camera); default 0.5 where looks vary (camera, shifted), 0 at "
        "clean",
    )
    gen.add_argument("--out", required=True, type=Path)
    gen.add_argument("--overwrite", action="store_true", help="replace an existing folder")
    gen.set_defaults(handler=cmd_data_generate)

    imp = data.add_parser(
        "import", help="recorded images + task.json + pairs.jsonl/csv -> OUT/train, OUT/test"
    )
    imp.add_argument("--from", dest="source", required=True, type=Path, help="folder to import")
    imp.add_argument("--out", required=True, type=Path)
    imp.add_argument("--name", help="task name instead of task.json's")
    imp.add_argument(
        "--test-fraction",
        type=float,
        default=0.2,
        help="share of the episodes held out when the rows give no split",
    )
    imp.add_argument("--seed", type=int, default=0, help="seed of the split by episode")
    imp.add_argument("--overwrite", action="store_true", help="replace an existing folder")
    imp.set_defaults(handler=cmd_data_import)

    exp = data.add_parser("export", help="dataset folders -> the import format (PNG + JSONL)")
    exp.add_argument(
        "--data", required=True, type=Path, action="append", help="dataset folder (repeatable)"
    )
    exp.add_argument("--out", required=True, type=Path)
    exp.add_argument("--overwrite", action="store_true", help="replace an existing folder")
    exp.set_defaults(handler=cmd_data_export)

    merge = data.add_parser(
        "merge",
        help="datasets of one task (a recording, its experience) -> one dataset to train on",
    )
    merge.add_argument(
        "--data", required=True, type=Path, action="append", help="dataset folder (repeatable)"
    )
    merge.add_argument("--out", required=True, type=Path)
    merge.add_argument("--overwrite", action="store_true", help="replace an existing folder")
    merge.set_defaults(handler=cmd_data_merge)
