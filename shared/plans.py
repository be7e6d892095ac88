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
    supports: list[int]  # training action pairs behind each step (the roadmap edges' weights)

    @property
    def confidence(self) -> float:
        """The product of the actions' confidences (1 without actions): the APN's view only;
        the reliability table in docs/serving/knowing.md shows it says nothing of the nodes."""
        return float(np.prod(self.confidences)) if self.confidences else 1.0

    @property
    def support(self) -> float:
        """How well the training data backs every step: the product over steps of (w + 1) /
        (w + 2), Laplace's rule of succession for a step seen w times and never seen to fail;
        so it falls with the plan's length and rises with each step's evidence
        (docs/serving/knowing.md, 'Plan confidence', for how often plans at each support are
        valid)."""
        return float(np.prod([(w + 1) / (w + 2) for w in self.supports]))

    def to_json(self, task: Task) -> dict[str, Any]:
        return {
            "nodes": self.nodes,
            "actions": [task.action_to_json(a) for a in self.actions],
            "confidences": [round(c, 6) for c in self.confidences],
            "confidence": round(self.confidence, 6),
            "supports": self.supports,
            "support": round(self.support, 6),
        }


@dataclass(frozen=True)
class Match:
    """How one image relates to the roadmap: `score` is the largest of its distance to the
    nearest node and its reconstruction errors, each over the model's calibrated threshold, so
    an image is known while it is at most 1."""

    known: bool
    score: float
    node: int

    def to_json(self) -> dict[str, Any]:
        return {"known": self.known, "score": round(self.score, 4), "node": self.node}

    @classmethod
    def from_json(cls, document: dict[str, Any]) -> Match:
        return cls(bool(document["known"]), float(document["score"]), int(document["node"]))


class UnknownImageError(Exception):
    """A planner refused to plan: `end` ("start" or "goal") is unlike what its model knows."""

    def __init__(self, end: str, reason: str, match: dict[str, Match]) -> None:
        super().__init__(reason)
        self.end = end
        self.reason = reason
        self.match = match


def refused_end(match: dict[str, Match]) -> str | None:
    """The first end that is not known, or None when both are."""
    return next((end for end in ("start", "goal") if not match[end].known), None)


def most_confident(plans: list[VisualActionPlan]) -> VisualActionPlan:
    """The plan whose first action the APN is surest of; the first plan on ties."""
    return max(plans, key=lambda p: p.confidences[0] if p.confidences else 1.0)
