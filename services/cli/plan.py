"""`lsr plan`: visual action plans in process, with contact sheets."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from services.cli.common import json_arg, single_thread_torch
from shared.settings import SHIPPED_MODEL


def _image_or_state(task, world, image: Path | None, state: str | None, rng, name: str):
    """A start or goal given as a PNG/JPEG file (a camera frame, registered to the table
    frame; an image at the model's size as it is) or as a state the sim shows."""
    from shared.images import decode_image
    from shared.registration import Registration, to_table_frame
    from shared.validation import MAX_FRAME

    if (image is None) == (state is None):
        raise ValueError(f"give exactly one of --{name}-image and --{name}-state")
    if image is not None:
        shown = decode_image(Path(image).read_bytes(), max_side=MAX_FRAME)
        registration = Registration(task.workcell, world.image_size)
        (registered,), (why,) = to_table_frame(registration, [shown])
        if why is not None:
            raise ValueError(f"--{name}-image is not known: {why}")
        return registered, None
    if world.task is None:
        raise ValueError(
            f"task {task.name!r} has no simulator to render --{name}-state; give --{name}-image"
        )
    from services.sim.workcell import Observer

    parsed = task.parse_state(json_arg(state))
    world.reset(parsed, rng)
    return Observer(world).see(), parsed


class _NoWorld:
    """Stands in for the world of a task without a simulator: images only."""

    task = None

    def __init__(self, planner) -> None:
        self.image_size = planner.image_size

    def __enter__(self) -> _NoWorld:
        return self

    def __exit__(self, *exc: object) -> None:
        pass


def cmd_plan(args: argparse.Namespace) -> int:
    import numpy as np
    from PIL import Image

    from services.encoder.checkpoint import read_vae_config
    from services.planner.action_plans import ActionPlanner
    from services.planner.sheets import plan_sheet, spec_action_pixels
    from services.sim.worlds import make_world
    from shared.appearance import trained_appearance
    from shared.plans import UnknownImageError
    from shared.tasks import has_simulator

    single_thread_torch()
    planner = ActionPlanner.from_model_dir(args.model)
    rng = np.random.default_rng(args.seed)
    looks = trained_appearance(read_vae_config(Path(args.model) / "vae"))  # as the model saw
    opened = (
        make_world(planner.task.name, planner.image_size, appearance=looks)
        if has_simulator(planner.task.name)
        else _NoWorld(planner)
    )
    with opened as world:
        start, _ = _image_or_state(
            planner.task, world, args.start_image, args.start_state, rng, "start"
        )
        goal, _ = _image_or_state(
            planner.task, world, args.goal_image, args.goal_state, rng, "goal"
        )
        z, errors = planner.planner.look(np.stack([start, goal]))
        matched = planner.planner.match(z[0], z[1], errors)
        reason = None
        try:
            plans = planner.plan_latent(z[0], z[1], args.max_plans, errors)
        except UnknownImageError as refused:
            plans, reason = [], refused.reason
        args.out.mkdir(parents=True, exist_ok=True)
        for k, plan in enumerate(plans):
            if world.task is None:  # a task defined by its data: its spec says where
                sheet = plan_sheet(
                    plan,
                    spec_action_pixels(planner.task, planner.image_size),
                    arrows=True,
                    text=lambda a: json.dumps(planner.task.action_to_json(a)),
                )
            else:
                sheet = plan_sheet(
                    plan,
                    world.action_pixels,
                    arrows=bool(world.task.spec.action.pixels),
                    text=world.task.action_label,
                )
            Image.fromarray(sheet).save(args.out / f"plan_{k}.png")
    summary: dict[str, Any] = {"plans": [p.to_json(planner.task) for p in plans]}
    if matched is not None:
        summary["match"] = {end: found.to_json() for end, found in matched.items()}
    if not plans:
        summary["reason"] = reason or "start and goal are not connected in the roadmap"
    (args.out / "plans.json").write_text(json.dumps(summary, indent=2) + "\n")
    if reason is not None:
        print(f"no plan: {reason}")
    print(f"{len(plans)} plan(s) written to {args.out}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    plan = sub.add_parser("plan", help="visual action plans from a start to a goal")
    plan.add_argument(
        "--model",
        type=Path,
        default=SHIPPED_MODEL,
        help="model folder (default: the shipped box-stacking model, wherever lsr is run from)",
    )
    plan.add_argument("--start-state", help="state JSON, inline or a file path")
    plan.add_argument("--start-image", type=Path, help="PNG or JPEG of the start")
    plan.add_argument("--goal-state", help="state JSON, inline or a file path")
    plan.add_argument("--goal-image", type=Path, help="PNG or JPEG of the goal")
    plan.add_argument("--max-plans", type=int, default=4)
    plan.add_argument("--seed", type=int, default=0, help="noise of rendered states")
    plan.add_argument("--out", required=True, type=Path)
    plan.set_defaults(handler=cmd_plan)
