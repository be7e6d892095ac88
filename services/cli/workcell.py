"""`lsr workcell`: the table's markers, as the tasks report them and as a sheet to print."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from shared.tasks import get_task, task_names
from shared.workcell import LAYOUTS, markers_svg


def cmd_layout(args: argparse.Namespace) -> int:
    from services.sim.workcell import layout
    from services.sim.worlds import make_world

    with make_world(args.task) as world:
        workcell = layout(world)
    text = json.dumps(workcell.to_json(), indent=2) + "\n"
    if args.write:
        path = LAYOUTS / f"{args.task}.json"
        path.write_text(text)
        print(f"wrote {path}")
    else:
        print(text, end="")
    return 0


def cmd_markers(args: argparse.Namespace) -> int:
    workcell = get_task(args.task).workcell
    if workcell is None:
        raise ValueError(f"task {args.task!r} has no workcell markers")
    out = Path(args.out)
    if out.suffix.lower() != ".svg":
        raise ValueError(f"--out: {out.name} is not an .svg file (the sheet is SVG, at true size)")
    out.write_text(markers_svg(workcell, args.task))
    sizes = sorted({m.side_mm for m in workcell.markers})
    print(f"wrote {out}: {len(workcell.markers)} markers ({workcell.dictionary}), sides {sizes} mm")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    group = sub.add_parser("workcell", help="the table's markers").add_subparsers(
        dest="sub", required=True
    )
    markers = group.add_parser("markers", help="write a printable sheet (SVG, true size)")
    markers.add_argument("--task", required=True, choices=task_names())
    markers.add_argument("--out", required=True, help="the .svg file to write")
    markers.set_defaults(handler=cmd_markers)
    design = group.add_parser(
        "layout", help="design a task's markers from its simulated camera (JSON)"
    )
    design.add_argument("--task", required=True, choices=task_names())
    design.add_argument("--write", action="store_true", help="write shared/tasks/workcells/")
    design.set_defaults(handler=cmd_layout)
