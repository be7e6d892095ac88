"""A task is its own files plus one registry line: generic code names no task.

What varies by task (d_m, the default look, the world's entry point, marker places, the minimum
markers) is declared by the task (`shared.tasks.base.Task`) or its world (`World`), so that a
new task plugs in without editing generic modules.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from services.encoder.train import TrainConfig
from services.sim.worlds import world_class
from shared.appearance import task_default
from shared.tasks import DEFAULT_TASK, declare_task, get_task, has_simulator, task_names
from shared.tasks.base import Task
from shared.tasks.spec import ArraySpec, TaskSpec

ROOT = Path(__file__).resolve().parents[1]


def owned(path: Path, task: str) -> bool:
    """A task's own files: its logic, its world's folder, its workcell."""
    relative = path.relative_to(ROOT).as_posix()
    return relative.startswith("shared/tasks/") or relative.startswith(f"services/sim/{task}/")


@pytest.mark.parametrize("task", task_names())
def test_no_generic_module_names_a_task(task):
    pattern = re.compile(rf"\b{task}\b")
    named = [
        f"{path.relative_to(ROOT)}:{number}: {line.strip()}"
        for package in ("services", "shared")
        for path in sorted((ROOT / package).rglob("*.py"))
        if not owned(path, task)
        for number, line in enumerate(path.read_text().splitlines(), start=1)
        if pattern.search(line)
    ]
    assert named == [], "declare it in the task (shared.tasks) or its world:\n" + "\n".join(named)


def test_every_task_declares_its_facts_and_a_task_from_data_takes_the_defaults():
    for name in task_names():
        task = get_task(name)
        assert set(task.d_m) == {"l1", "l2", "inf"}
        assert has_simulator(name) and world_class(name).marker_places
        assert TrainConfig(metric="l1").d_m(name) == task.d_m["l1"]
        assert task_default(name) == task.default_look
    assert DEFAULT_TASK in task_names()
    action = ArraySpec(dtype="int64", shape=(2,), names=("from", "to"), counts=(4, 4))
    spec = TaskSpec(task="pushing_blocks", action=action, state=None)
    data_task = declare_task(spec)
    assert data_task.world_entry is None and not has_simulator("pushing_blocks")
    assert TrainConfig(metric="l2").d_m("pushing_blocks") == Task.d_m["l2"]
    assert task_default("pushing_blocks") == "clean"
