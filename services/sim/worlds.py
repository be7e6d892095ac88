"""World registry: the physical simulation of each task, by task name.

Entry points are "module:Class" strings (as Gymnasium's `register`), imported on first use, so
that naming a task never loads MuJoCo.
"""

from __future__ import annotations

import importlib
from typing import Any

from shared.tasks import get_task
from shared.tasks.base import World

_WORLDS: dict[str, str] = {
    "box_stacking": "services.sim.box_stacking.world:BoxStackingWorld",
    "cloth_folding": "services.sim.cloth_folding.world:ClothFoldingWorld",
    "tshirt_folding": "services.sim.tshirt_folding.world:TshirtFoldingWorld",
}


def has_world(task_name: str) -> bool:
    return task_name in _WORLDS


def world_class(task_name: str) -> type[World]:
    get_task(task_name)  # raises TaskError naming the known tasks
    if task_name not in _WORLDS:
        raise NotImplementedError(f"task {task_name!r} has no simulated world")
    module, name = _WORLDS[task_name].split(":")
    return getattr(importlib.import_module(module), name)


def make_world(
    task_name: str, image_size: int = 64, appearance: str | None = None, **options: Any
) -> World:
    """The task's world; `options` go to its constructor (e.g. a cloth's `lattice`). With an
    `appearance` level (shared.appearance), the world seen through its modder (at `clean`, a
    wrapper rendering exactly what the world does)."""
    world = world_class(task_name)(get_task(task_name), image_size=image_size, **options)
    if appearance is None:
        return world
    from services.sim.appearance import AppearanceWorld

    return AppearanceWorld(world, appearance)
