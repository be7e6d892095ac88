"""`lsr task`: task descriptions."""

from __future__ import annotations

import argparse
import json

from shared.tasks import get_task, task_names


def cmd_task_info(args: argparse.Namespace) -> int:
    print(json.dumps(get_task(args.task).info(), indent=2))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    task = sub.add_parser("task", help="task descriptions").add_subparsers(
        dest="sub", required=True
    )
    info = task.add_parser("info", help="print a task's description as JSON")
    info.add_argument("task", choices=task_names())
    info.set_defaults(handler=cmd_task_info)
