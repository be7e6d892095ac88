"""World registry: the physical simulation of each task, by task name."""

from __future__ import annotations

from shared.tasks import get_task
from shared.tasks.base import World


def make_world(task_name: str, image_size: int = 64) -> World:
    task = get_task(task_name)  # raises TaskError naming the known tasks
    if task_name == "box_stacking":
        from services.sim.box_stacking.world import BoxStackingWorld

        return BoxStackingWorld(task, image_size=image_size)  # type: ignore[arg-type]
    raise NotImplementedError(f"task {task_name!r} has no simulated world yet")
