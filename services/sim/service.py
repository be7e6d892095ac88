"""The sim service: renders states and runs closed-loop episodes in MuJoCo physics.

An episode plans through the encoder, planner and APN services like any other client, so the
sim holds no model: only the image size it must render at.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from services.runtime import ServiceContext
from services.sim.appearance import AppearanceWorld
from services.sim.closed_loop import run_episode
from services.sim.settled import FOLDER, default_folders, ensure_complete
from services.sim.workcell import Observer
from services.sim.worlds import make_world, world_class
from shared.bus import MSGPACK, Handler, progress_key
from shared.client import PlanningClient
from shared.messages import (
    PixelsReply,
    PixelsRequest,
    RenderReply,
    RenderRequest,
    RunReply,
    RunRequest,
    RunStep,
    WireArray,
    pack,
    unpack,
)
from shared.tasks import get_task
from shared.tasks.base import World
from shared.validation import (
    FieldError,
    check_appearance,
    check_task,
    decode_frame,
    parse_state,
)

log = logging.getLogger(__name__)


def world_maker(task_name: str, size: int, model_dir: Path) -> Callable[[], World]:
    """Worlds of the served task. One that settles searches the served model's library first
    (MODEL/settled), then the shipped models' and the cache's; it is made complete here, before
    serving (built with a progress bar and kept in the cache when no folder has this scene's),
    so that every operation's world loads it and resets in milliseconds."""
    if not world_class(task_name).settles:
        return lambda: make_world(task_name, size)
    folders = [model_dir / FOLDER, *default_folders()]
    with make_world(task_name, size, library=folders) as world:
        library = world.library  # type: ignore[attr-defined]
        ensure_complete(world, library)
        log.info("settled states of %s from %s", task_name, library.source)
    folders.insert(0, library.source)
    return lambda: make_world(task_name, size, library=folders)


def setup(context: ServiceContext) -> dict[str, Handler]:
    name, size = context.model.task, context.model.image_size
    task = get_task(name)
    # One world per operation, made by that operation's worker thread on first use: an EGL
    # context can only be current in one thread, and the worker is the thread that renders.
    # Each is seen at a request's appearance level, by default the model's training one.
    worlds: dict[str, AppearanceWorld] = {}
    new_world = world_maker(name, size, context.model.directory)
    trained = context.model.appearance

    def world(operation: str, appearance: str = trained) -> AppearanceWorld:
        if operation not in worlds:
            worlds[operation] = AppearanceWorld(new_world())
        worlds[operation].use(appearance)
        return worlds[operation]

    planner = PlanningClient(context.session, name, context.settings.deadline_s)

    def render(payload: bytes) -> RenderReply:
        request = unpack(payload, RenderRequest)
        check_task(request.task, name)
        states = [parse_state(task, f"states.{i}", s) for i, s in enumerate(request.states)]
        appearance = check_appearance(request.appearance, trained)
        rng = np.random.default_rng(request.seed)
        render_world = world("render", appearance)
        observer = Observer(render_world)  # the view as the model is given it: registered
        images = []
        for state in states:
            render_world.reset(state, rng)
            images.append(render_world.frame() if request.frame else observer.look()[0])
        return RenderReply(images=WireArray.of(np.stack(images)))

    def run(payload: bytes) -> RunReply:
        request = unpack(payload, RunRequest)
        check_task(request.task, name)
        start = parse_state(task, "start", request.start)
        goal = (
            None
            if request.goal_state is None
            else parse_state(task, "goal_state", request.goal_state)
        )
        goal_image = None
        if request.goal_image is not None:
            goal_image = decode_frame("goal_image", request.goal_image)  # registered in the loop
        if (goal is None) == (goal_image is None):
            raise FieldError("goal_state", "give exactly one of goal_state and goal_image")
        run_world = world("run", check_appearance(request.appearance, trained))
        on_step = None
        if request.progress is not None:
            key = progress_key(name, request.progress)

            def on_step(step: int, action: Any, state: Any, image: np.ndarray) -> None:
                # What the camera sees now: the image the episode has just recorded.
                message = RunStep(
                    step=step,
                    action=task.action_to_json(action),
                    state=task.state_to_json(state),
                    image=WireArray.of(image),
                )
                try:
                    context.session.put(key, pack(message), encoding=MSGPACK)
                except zenoh.ZError:  # progress is a courtesy: the episode goes on without it
                    log.warning("could not publish step %d on %s", step, key)

        episode = run_episode(
            planner,
            run_world,
            start,
            goal,
            np.random.default_rng(request.seed),
            goal_image=goal_image,
            max_steps=request.max_steps,
            max_plans=request.max_plans,
            on_step=on_step,
        )
        images = np.stack(episode.images) if episode.images else np.zeros((0, size, size, 3))
        return RunReply(
            success=episode.success,
            reason=episode.reason,
            detail=episode.detail,
            final_state=(
                None if episode.final_state is None else task.state_to_json(episode.final_state)
            ),
            final_view=(
                None if episode.final_state is None else task.view_to_json(episode.final_state)
            ),
            actions=[task.action_to_json(a) for a in episode.actions],
            images=WireArray.of(images.astype(np.uint8)),
        )

    def pixels(payload: bytes) -> PixelsReply:
        request = unpack(payload, PixelsRequest)
        check_task(request.task, name)
        actions = [task.parse_action(a) for a in request.actions]
        pixels_world = world("pixels")
        marks = [[*pick, *release] for pick, release in map(pixels_world.action_pixels, actions)]
        return PixelsReply(pixels=WireArray.of(np.asarray(marks, np.float32)), image_size=size)

    return {"render": render, "run": run, "pixels": pixels}
