"""The `lsr` command line: one entry point for every part of the project.

Each command group lives in its own module with its handlers and a `register(sub)` that adds
its arguments; handlers map flags onto the self-validating config dataclasses of the code they
call.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable

from services.cli import data, evaluate, plan, roadmap, robot, serve, sim, task, train, workcell

Handler = Callable[[argparse.Namespace], int]
GROUPS = (task, data, train, roadmap, evaluate, plan, sim, serve, robot, workcell)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="lsr", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    for group in GROUPS:
        group.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    handler: Handler = args.handler
    try:
        return handler(args)
    except (ValueError, FileExistsError, FileNotFoundError, NotImplementedError) as exc:
        print(f"lsr: error: {exc}", file=sys.stderr)
        return 2
