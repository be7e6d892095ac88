"""`lsr render`, `lsr demo` and `lsr settle`: the simulated worlds, their pictures and states."""

from __future__ import annotations

import argparse
from pathlib import Path

from services.cli.common import json_arg
from shared.appearance import LEVELS, levels_help, task_default
from shared.tasks import DEFAULT_TASK, get_task, task_names

DEMO_STATES = 36  # `lsr demo` shows every state of a task with at most this many, else 5


def cmd_render(args: argparse.Namespace) -> int:
    import numpy as np
    from PIL import Image

    from services.sim.worlds import make_world

    task = get_task(args.task)
    state = task.parse_state(json_arg(args.state))
    appearance = args.appearance or task_default(args.task)
    with make_world(args.task, args.size, appearance=appearance) as world:
        world.reset(state, np.random.default_rng(args.seed))
        Image.fromarray(world.render()).save(args.out)
    print(f"wrote {args.out}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """A contact sheet of rendered states: box stacking, five states and one executed move;
    cloth folding, the whole state family."""
    import numpy as np
    from PIL import Image

    from services.sim.worlds import make_world
    from shared.images import contact_sheet

    task = get_task(args.task)
    rng = np.random.default_rng(args.seed)
    states = task.all_states()
    images, labels = [], []
    with make_world(args.task, args.size, appearance=task_default(args.task)) as world:
        if len(states) > DEMO_STATES:  # a sample of them
            picks = [states[i] for i in rng.choice(len(states), size=5, replace=False)]
            what, columns = "5 rendered states and the last one after a move", 3
        else:
            picks = list(states)
            what, columns = f"all {len(picks)} states and the last one after a move", 6
        for state in picks:
            world.reset(state, rng)
            images.append(world.render())
            labels.append(task.state_label(state))
        action = task.legal_actions(picks[-1])[0]
        world.execute(world.demonstrated(action, rng), rng)
        images.append(world.render())
        labels.append(task.action_label(action))
    out = args.out or Path("docs/images") / f"{args.task}_states.png"
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(contact_sheet(images, columns=columns, labels=labels)).save(out)
    print(f"wrote {out}: {what}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    render = sub.add_parser("render", help="render one state to a PNG")
    render.add_argument("--task", default=DEFAULT_TASK, choices=task_names())
    render.add_argument("--state", required=True, help="state JSON, inline or a file path")
    render.add_argument("--seed", type=int, default=0)
    render.add_argument("--size", type=int, default=64)
    render.add_argument(
        "--appearance",
        default=None,
        choices=LEVELS,
        help=f"how the image looks; default: the task's ({levels_help()})",
    )
    render.add_argument("--out", required=True, type=Path)
    render.set_defaults(handler=cmd_render)

    settle = sub.add_parser(
        "settle",
        help="fold every state of a deformable world once and save its settled-state library",
    )
    settle.add_argument("--task", required=True, choices=task_names(), help="a world that settles")
    settle.add_argument("--lattice", type=int, help="cloth vertices along a side (tests)")
    settle.add_argument("--out", type=Path, help="library folder (default: in the cache)")
    settle.add_argument("--rebuild", action="store_true", help="fold every state again")
    settle.add_argument("--json", action="store_true", help="no progress bar")
    settle.set_defaults(handler=cmd_settle)

    demo = sub.add_parser("demo", help="render a contact sheet of a few states")
    demo.add_argument("--task", default=DEFAULT_TASK, choices=task_names())
    demo.add_argument("--out", type=Path, help="default: docs/images/TASK_states.png")
    demo.add_argument("--size", type=int, default=128)
    demo.add_argument("--seed", type=int, default=0)
    demo.set_defaults(handler=cmd_demo)


def cmd_settle(args: argparse.Namespace) -> int:
    """Build a world's settled-state library: every state folded once, saved sealed."""
    import json

    from services.sim.settled import cached_folder
    from services.sim.worlds import make_world, world_class

    if not world_class(args.task).settles:
        raise ValueError(f"task {args.task!r}: its world resets without a library")
    options = {} if args.lattice is None else {"lattice": args.lattice}
    with make_world(args.task, 64, **options) as world:
        library = world.library  # type: ignore[attr-defined]
        if args.rebuild:
            library.physics.clear()
        library.fill(world, progress=not args.json)
        out = library.save(args.out or cached_folder(library.scene_hash))
    summary = {
        "task": args.task,
        "scene_hash": library.scene_hash,
        "orders": len(library.physics),
        "build_seconds": round(library.build_seconds, 1),
        "out": str(out),
    }
    print(json.dumps(summary))
    return 0
