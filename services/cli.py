"""The `lsr` command line: one entry point for every part of the project."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from shared.tasks import get_task, task_names

Handler = Callable[[argparse.Namespace], int]


def _json_arg(text: str) -> Any:
    """JSON given inline, or the path of a JSON file."""
    source = Path(text).read_text() if not text.lstrip().startswith(("{", "[")) else text
    try:
        return json.loads(source)
    except json.JSONDecodeError as exc:
        raise ValueError(f"not valid JSON: {exc}") from None


def cmd_task_info(args: argparse.Namespace) -> int:
    print(json.dumps(get_task(args.task).info(), indent=2))
    return 0


def cmd_data_generate(args: argparse.Namespace) -> int:
    from services.sim.datagen import GenerateConfig, generate

    cfg = GenerateConfig(
        task=args.task,
        pairs=args.pairs,
        seed=args.seed,
        image_size=args.size,
        action_fraction=args.action_fraction,
        workers=args.workers,
    )
    result = generate(cfg, args.out, overwrite=args.overwrite)
    counts = result["counts"]
    print(
        f"wrote {counts['tuples']} tuples ({counts['action_pairs']} action, "
        f"{counts['no_action_pairs']} no-action) to {args.out} in {result['seconds']:.1f} s "
        f"({result['images_per_second']:.0f} images/s)"
    )
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    import numpy as np
    from PIL import Image

    from services.sim.worlds import make_world

    task = get_task(args.task)
    state = task.parse_state(_json_arg(args.state))
    with make_world(args.task, args.size) as world:
        world.reset(state, np.random.default_rng(args.seed))
        Image.fromarray(world.render()).save(args.out)
    print(f"wrote {args.out}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """Render a few states and one executed move into a contact sheet."""
    import numpy as np
    from PIL import Image

    from services.sim.worlds import make_world
    from shared.images import contact_sheet

    task = get_task("box_stacking")
    rng = np.random.default_rng(args.seed)
    states = task.all_states()
    picks = [states[i] for i in rng.choice(len(states), size=5, replace=False)]
    images, labels = [], []
    with make_world("box_stacking", args.size) as world:
        for state in picks:
            world.reset(state, rng)
            images.append(world.render())
            labels.append(" | ".join(",".join(b[0].upper() for b in col) or "-" for col in state))
        state = picks[-1]
        action = task.legal_actions(state)[0]
        world.execute(action, rng)
        images.append(world.render())
        labels.append(
            f"({action.pick.row},{action.pick.col})->({action.release.row},{action.release.col})"
        )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(contact_sheet(images, columns=3, labels=labels)).save(out)
    print(f"wrote {out}: 5 rendered states and the last one after a move")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="lsr", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    task = sub.add_parser("task", help="task descriptions").add_subparsers(
        dest="sub", required=True
    )
    info = task.add_parser("info", help="print a task's description as JSON")
    info.add_argument("task", choices=task_names())
    info.set_defaults(handler=cmd_task_info)

    data = sub.add_parser("data", help="datasets").add_subparsers(dest="sub", required=True)
    gen = data.add_parser("generate", help="render a dataset of action and no-action pairs")
    gen.add_argument("--task", default="box_stacking", choices=task_names())
    gen.add_argument("--pairs", type=int, default=5000, help="number of tuples")
    gen.add_argument("--seed", type=int, default=0)
    gen.add_argument("--size", type=int, default=64, help="image size in pixels (square)")
    gen.add_argument("--action-fraction", type=float, default=0.65)
    gen.add_argument("--workers", type=int, default=2, help="rendering processes")
    gen.add_argument("--out", required=True, type=Path)
    gen.add_argument("--overwrite", action="store_true", help="replace an existing folder")
    gen.set_defaults(handler=cmd_data_generate)

    render = sub.add_parser("render", help="render one state to a PNG")
    render.add_argument("--task", default="box_stacking", choices=task_names())
    render.add_argument("--state", required=True, help="state JSON, inline or a file path")
    render.add_argument("--seed", type=int, default=0)
    render.add_argument("--size", type=int, default=64)
    render.add_argument("--out", required=True, type=Path)
    render.set_defaults(handler=cmd_render)

    demo = sub.add_parser("demo", help="render a contact sheet of a few states")
    demo.add_argument("--out", type=Path, default=Path("docs/images/box_stacking_states.png"))
    demo.add_argument("--size", type=int, default=128)
    demo.add_argument("--seed", type=int, default=0)
    demo.set_defaults(handler=cmd_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    handler: Handler = args.handler
    try:
        return handler(args)
    except (ValueError, FileExistsError, FileNotFoundError, NotImplementedError) as exc:
        print(f"lsr: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
