"""`lsr workcell`: the table's markers, as the tasks report them and as sheets to print.

Built-in tasks carry their layout (`shared/tasks/workcells/`); a task known only from its data
carries it in its `task.json` (`"markers"`), and a dataset imported from it in its manifest.
`layout` designs one (from a built-in task's simulated camera, or for a rectangle of your own
table), `markers` prints it, `check` registers one camera frame with it.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from shared.tasks import get_task, task_names
from shared.workcell import DICTIONARY, LAYOUTS, Workcell, markers_svg, rectangle_layout


def cmd_layout(args: argparse.Namespace) -> int:
    if args.table_mm is not None:
        return _custom_layout(args)
    if args.marker_mm is not None or args.inset_mm is not None or args.task_json is not None:
        raise ValueError(
            "--marker-mm, --inset-mm and --task-json go with --table-mm (a table of your own)"
        )
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


def _custom_layout(args: argparse.Namespace) -> int:
    """A rectangle's corner markers as task.json's `"markers"` section: printed, or set in a
    task.json (checked as `lsr data import` checks it)."""
    if args.write:
        raise ValueError("--write is for a built-in task's layout; use --task-json PATH")
    if args.marker_mm is None:
        raise ValueError("--table-mm needs --marker-mm (the markers' side, border included)")
    workcell = rectangle_layout(
        tuple(args.table_mm), args.marker_mm, args.inset_mm, dictionary=args.dictionary
    )
    section = workcell.to_json()
    if args.task_json is None:
        print(json.dumps(section, indent=2))
        return 0
    from shared.tasks.declared import DeclarationError, TaskDeclaration

    path = Path(args.task_json)
    try:
        obj = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(obj, dict):
        raise ValueError(f"{path}: expected a JSON object")
    obj["markers"] = section
    try:
        TaskDeclaration.from_json(obj)
    except DeclarationError as exc:
        raise ValueError(f"{path}: {exc} (nothing written)") from None
    path.write_text(json.dumps(obj, indent=2) + "\n")
    width, height = args.table_mm
    print(
        f"wrote the markers of a {width:g} x {height:g} mm table into {path}: "
        f"{len(workcell.markers)} markers of {args.marker_mm:g} mm"
    )
    return 0


def source_workcell(args: argparse.Namespace) -> tuple[Workcell, str]:
    """The markers that `--task`, `--task-json` or `--data` name, and the task's name."""
    if args.task is not None:
        name, workcell = args.task, get_task(args.task).workcell
    elif args.task_json is not None:
        name, workcell = _from_task_json(Path(args.task_json))
    else:
        name, workcell = _from_data(Path(args.data))
    if workcell is None:
        raise ValueError(
            f'task {name!r} has no markers ("markers": null: a camera that never moves); '
            "design them with lsr workcell layout --table-mm W H --marker-mm S"
        )
    return workcell, name


def _from_task_json(path: Path) -> tuple[str, Workcell | None]:
    from shared.workcell import WorkcellError

    try:
        obj = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(obj, dict) or "markers" not in obj:
        raise ValueError(f'{path}: no "markers" section (lsr workcell layout writes one)')
    try:
        return str(obj.get("name", path.parent.name)), Workcell.from_json(obj["markers"])
    except WorkcellError as exc:
        raise ValueError(f"{path}: {exc}") from None


def _from_data(directory: Path) -> tuple[str, Workcell | None]:
    """A dataset's markers (its manifest); an import's folder (OUT with OUT/train, OUT/test)
    is read through the task.json it keeps."""
    from shared.dataset import read_manifest

    if not (directory / "manifest.json").is_file() and (directory / "task.json").is_file():
        return _from_task_json(directory / "task.json")
    manifest = read_manifest(directory)
    if "markers" not in manifest:
        raise ValueError(f"{directory}: its manifest records no markers (made before markers)")
    return str(manifest.get("task")), Workcell.from_json(manifest["markers"], "manifest.markers")


def cmd_markers(args: argparse.Namespace) -> int:
    workcell, name = source_workcell(args)
    out = Path(args.out)
    title = f"LSR markers: {name} ({workcell.dictionary})"
    if args.paper == "none":
        if out.suffix.lower() != ".svg":
            raise ValueError(f"--out: {out.name} is not an .svg file (--paper none: one SVG)")
        out.write_text(markers_svg(workcell, name))
        sizes = sorted({m.side_mm for m in workcell.markers})
        print(
            f"wrote {out}: {len(workcell.markers)} markers ({workcell.dictionary}), sides "
            f"{sizes} mm, one sheet at true size: print it at 100% on paper that large"
        )
        return 0
    from shared.marker_sheets import instructions, write_sheets

    paths, tiling = write_sheets(workcell, title, out, args.paper)
    written = str(paths[0]) if len(paths) == 1 else f"{paths[0]} ... {paths[-1].name}"
    print(f"wrote {written}: {len(workcell.markers)} markers ({workcell.dictionary})")
    for line in instructions(workcell, tiling):
        print(line)
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    """Register one camera frame as import and serving will, and show the view it gives."""
    import numpy as np
    from PIL import Image

    from shared.images import decode_image
    from shared.registration import Registration

    workcell, name = source_workcell(args)
    frame = decode_image(Path(args.image).read_bytes(), at_least=None)
    registered = Registration(workcell, args.size).register(frame)
    Image.fromarray(np.asarray(registered.image)).save(args.out)
    print(
        json.dumps(
            {
                "task": name,
                "frame": [int(frame.shape[1]), int(frame.shape[0])],
                "markers_found": list(registered.found),
                "corner_error_px": round(registered.error_px, 3),
                "view_moved_px": round(registered.offset_px, 2),
                "out": str(args.out),
            }
        )
    )
    return 0


def _sources(parser: argparse.ArgumentParser) -> None:
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--task", choices=task_names(), help="a built-in task")
    source.add_argument(
        "--task-json", help='a task.json with a "markers" section (a task known from its data)'
    )
    source.add_argument(
        "--data",
        help="a dataset whose manifest records markers (lsr data import's OUT/train, or OUT)",
    )


def register(sub: argparse._SubParsersAction) -> None:
    group = sub.add_parser("workcell", help="the table's markers").add_subparsers(
        dest="sub", required=True
    )
    markers = group.add_parser(
        "markers", help="write the markers to print: pages of A4 or Letter, or one true-size SVG"
    )
    _sources(markers)
    markers.add_argument(
        "--paper",
        choices=("a4", "letter", "none"),
        default="a4",
        help="a4 (default) or letter: the sheet tiled on pages that print at 100%%, every "
        "marker whole on one; none: one SVG of the whole sheet at true size",
    )
    markers.add_argument(
        "--out",
        required=True,
        help="OUT.pdf: one PDF, a page a tile; OUT.svg: OUT_p1.svg, OUT_p2.svg, ... "
        "(with --paper none: OUT.svg itself)",
    )
    markers.set_defaults(handler=cmd_markers)

    design = group.add_parser(
        "layout",
        help="design markers (JSON): from a built-in task's simulated camera (--task), or "
        "at the corners of your own table (--table-mm W H --marker-mm S)",
    )
    what = design.add_mutually_exclusive_group(required=True)
    what.add_argument("--task", choices=task_names(), help="a built-in task: from its scene")
    what.add_argument(
        "--table-mm",
        nargs=2,
        type=float,
        metavar=("W", "H"),
        help="your table's rectangle (mm; W across the camera's view, H away from it): a "
        "marker inside each corner, the view looking straight down on it",
    )
    design.add_argument(
        "--write", action="store_true", help="with --task: write shared/tasks/workcells/"
    )
    design.add_argument(
        "--marker-mm", type=float, help="with --table-mm: each marker's side, border included"
    )
    design.add_argument(
        "--inset-mm",
        type=float,
        help="with --table-mm: from each marker's outer edges to the table's (default: a "
        "sixth of the marker, one of its cells: the white margin the detector wants)",
    )
    design.add_argument(
        "--dictionary",
        choices=(DICTIONARY,),
        default=DICTIONARY,
        help="the ArUco dictionary (the one registration supports)",
    )
    design.add_argument(
        "--task-json",
        help='with --table-mm: set this task.json\'s "markers" (checked as lsr data import '
        "checks it) instead of printing the section",
    )
    design.set_defaults(handler=cmd_layout)

    check = group.add_parser(
        "check", help="register one camera frame to the table frame and write the view it gives"
    )
    _sources(check)
    check.add_argument("--image", required=True, help="a camera frame (PNG or JPEG)")
    check.add_argument("--size", type=int, default=256, help="the view's size (default 256)")
    check.add_argument("--out", required=True, help="the registered view (PNG)")
    check.set_defaults(handler=cmd_check)
