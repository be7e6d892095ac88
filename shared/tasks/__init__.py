"""Task registry: the logic of every task the project knows, by name."""

from __future__ import annotations

from collections.abc import Callable
from functools import cache

from shared.tasks.base import Task, TaskError
from shared.tasks.box_stacking import BoxStacking
from shared.tasks.cloth_folding import ClothFolding

_TASKS: dict[str, Callable[[], Task]] = {"box_stacking": BoxStacking, "cloth_folding": ClothFolding}


def task_names() -> list[str]:
    return sorted(_TASKS)


@cache
def get_task(name: str) -> Task:
    """The task's logic; one shared instance per name (tasks hold no mutable state)."""
    try:
        return _TASKS[name]()
    except KeyError:
        raise TaskError(f"unknown task {name!r}; known tasks are {task_names()}") from None
