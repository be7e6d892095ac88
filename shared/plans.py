"""Visual action plans as every part of the system passes them around."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from shared.tasks.base import Task


@dataclass
class VisualActionPlan:
    nodes: list[int]  # roadmap node ids, start to goal
    images: list[np.ndarray]  # decoded node images, one more than actions (empty if not asked)
    actions: list[Any]  # the task's actions between consecutive images
    confidences: list[float]  # the APN's confidence in each action

    def to_json(self, task: Task) -> dict[str, Any]:
        return {
            "nodes": self.nodes,
            "actions": [task.action_to_json(a) for a in self.actions],
            "confidences": [round(c, 6) for c in self.confidences],
        }


def most_confident(plans: list[VisualActionPlan]) -> VisualActionPlan:
    """The plan whose first action the APN is surest of; the first plan on ties."""
    return max(plans, key=lambda p: p.confidences[0] if p.confidences else 1.0)
