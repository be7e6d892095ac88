"""Task registry: the logic of every task the project knows, by name.

Built-in tasks are classes with rules and a simulator. Tasks defined by their data (imported
datasets) join at run time: whoever reads such a dataset or model declares its spec here
(`declare_task`), and `get_task` then answers for it like for a built-in one.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import cache

from shared.tasks.base import Task, TaskError
from shared.tasks.box_stacking import BoxStacking
from shared.tasks.cloth_folding import ClothFolding
from shared.tasks.declared import DataTask
from shared.tasks.rope_box import RopeBox
from shared.tasks.spec import TaskSpec
from shared.tasks.tshirt_folding import TshirtFolding
from shared.workcell import Workcell

_TASKS: dict[str, Callable[[], Task]] = {
    "box_stacking": BoxStacking,
    "cloth_folding": ClothFolding,
    "rope_box": RopeBox,
    "tshirt_folding": TshirtFolding,
}
_DECLARED: dict[str, DataTask] = {}
# What commands and settings take when no task is named: the paper's first study.
DEFAULT_TASK = "box_stacking"


def task_names() -> list[str]:
    """The built-in tasks (those with rules and a simulator)."""
    return sorted(_TASKS)


def known_tasks() -> list[str]:
    """Built-in tasks and the tasks this process has declared from data."""
    return sorted({*_TASKS, *_DECLARED})


def get_task(name: str) -> Task:
    """The task's logic; one shared instance per name (tasks hold no mutable state)."""
    declared = _DECLARED.get(name)
    return declared if declared is not None else _builtin(name)


@cache
def _builtin(name: str) -> Task:
    try:
        return _TASKS[name]()
    except KeyError:
        raise TaskError(f"unknown task {name!r}; known tasks are {known_tasks()}") from None


def declare_task(spec: TaskSpec, workcell: Workcell | None = None) -> Task:
    """The task of a dataset's or model's spec: the built-in one of that name, else a
    data-only task made from the spec and its data's markers (and remembered, so that
    `get_task` finds it)."""
    if spec.task in _TASKS:
        return get_task(spec.task)
    known = _DECLARED.get(spec.task)
    if known is not None and known.spec != spec:
        raise TaskError(f"task {spec.task!r} is already declared with another spec")
    if known is not None and workcell is not None and known.workcell != workcell:
        raise TaskError(f"task {spec.task!r} is already declared with other markers")
    if known is None:
        known = _DECLARED[spec.task] = DataTask(spec, workcell)
    return known


def has_simulator(name: str) -> bool:
    """Whether a World exists for the task (data-only tasks have none)."""
    return name in _TASKS and _builtin(name).world_entry is not None
