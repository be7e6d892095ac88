"""The diamond-shaped MLP of paper section V, with a classification or a regression head."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Literal

import torch
from torch import nn
from torch.nn import functional as F

Head = Literal["classify", "regress", "hybrid"]
HYBRID_MAX_CLASSES = 16  # hybrid: elements with more values than this are regressed


@dataclass(frozen=True)
class APNConfig:
    latent_dim: int = 64
    action_sizes: tuple[int, ...] = (3, 3, 3, 3)  # values per action-array element
    head: Head = "classify"
    width: int = 64
    branch: int = 16

    def __post_init__(self) -> None:
        if self.head not in ("classify", "regress", "hybrid"):
            raise ValueError(f"head must be classify, regress or hybrid, got {self.head!r}")

    @property
    def regressed(self) -> tuple[bool, ...]:
        """Per action element: regressed (a sigmoid scaled to its range) or classified."""
        if self.head == "hybrid":
            return tuple(n > HYBRID_MAX_CLASSES for n in self.action_sizes)
        return (self.head == "regress",) * len(self.action_sizes)

    def to_dict(self) -> dict:
        return asdict(self)


class APN(nn.Module):
    """z1 and z2 share a first layer, pass separate branches, meet, and narrow to the action."""

    def __init__(self, config: APNConfig) -> None:
        super().__init__()
        self.config = config
        self.shared = nn.Linear(config.latent_dim, config.width)
        self.branch1 = nn.Linear(config.width, config.branch)
        self.branch2 = nn.Linear(config.width, config.branch)
        self.joint = nn.Linear(2 * config.branch, config.branch)
        # One output per regressed element, one logit per value of a classified one.
        self.widths = [
            1 if r else n for r, n in zip(config.regressed, config.action_sizes, strict=True)
        ]
        self.out = nn.Linear(config.branch, sum(self.widths))

    def forward(self, z1: torch.Tensor, z2: torch.Tensor) -> torch.Tensor:
        h1 = F.relu(self.branch1(F.relu(self.shared(z1))))
        h2 = F.relu(self.branch2(F.relu(self.shared(z2))))
        return self.out(F.relu(self.joint(torch.cat([h1, h2], dim=-1))))

    def loss(self, output: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """target: integer action arrays (B, len(action_sizes)). Mean over the elements of the
        squared error of each regressed one (scaled to [0, 1]) and the cross-entropy of each
        classified one."""
        terms = []
        parts = output.split(self.widths, dim=-1)
        for i, (x, regressed, size) in enumerate(
            zip(parts, self.config.regressed, self.config.action_sizes, strict=True)
        ):
            if regressed:
                scaled = target[:, i].float() / max(size - 1, 1)
                terms.append(F.mse_loss(torch.sigmoid(x[:, 0]), scaled))
            else:
                terms.append(F.cross_entropy(x, target[:, i]))
        return sum(terms) / len(terms)

    def predict(self, output: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Integer action arrays and a confidence per prediction: the product of the classified
        elements' probabilities, and for a regress head of how clearly each value rounds."""
        actions, confidence = [], torch.ones(len(output))
        parts = output.split(self.widths, dim=-1)
        for x, regressed, size in zip(
            parts, self.config.regressed, self.config.action_sizes, strict=True
        ):
            if regressed:
                value = torch.sigmoid(x[:, 0]) * (size - 1)
                action = value.round().long().clamp(0, size - 1)
                if self.config.head == "regress":
                    confidence = confidence * (1 - 2 * (value - action).abs()).clamp(min=0)
            else:
                best = F.softmax(x, -1).max(-1)
                action = best.indices
                confidence = confidence * best.values
            actions.append(action)
        return torch.stack(actions, dim=-1), confidence
