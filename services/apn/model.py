"""The diamond-shaped MLP of paper section V, with a classification or a regression head."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Literal

import torch
from torch import nn
from torch.nn import functional as F

Head = Literal["classify", "regress"]


@dataclass(frozen=True)
class APNConfig:
    latent_dim: int = 64
    action_sizes: tuple[int, ...] = (3, 3, 3, 3)  # values per action-array element
    head: Head = "classify"
    width: int = 64
    branch: int = 16

    def __post_init__(self) -> None:
        if self.head not in ("classify", "regress"):
            raise ValueError(f"head must be classify or regress, got {self.head!r}")

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
        outputs = (
            sum(config.action_sizes) if config.head == "classify" else len(config.action_sizes)
        )
        self.out = nn.Linear(config.branch, outputs)

    def forward(self, z1: torch.Tensor, z2: torch.Tensor) -> torch.Tensor:
        h1 = F.relu(self.branch1(F.relu(self.shared(z1))))
        h2 = F.relu(self.branch2(F.relu(self.shared(z2))))
        return self.out(F.relu(self.joint(torch.cat([h1, h2], dim=-1))))

    def loss(self, output: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        """target: integer action arrays (B, len(action_sizes))."""
        if self.config.head == "regress":
            return F.mse_loss(torch.sigmoid(output), self._scale(target))
        logits = output.split(list(self.config.action_sizes), dim=-1)
        return sum(F.cross_entropy(x, target[:, i]) for i, x in enumerate(logits)) / len(logits)

    def predict(self, output: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Integer action arrays and a confidence per prediction (product of probabilities)."""
        sizes = torch.tensor(self.config.action_sizes)
        if self.config.head == "regress":
            value = torch.sigmoid(output) * (sizes - 1)
            action = value.round().long().clamp(min=0, max=None)
            action = torch.minimum(action, sizes - 1)
            confidence = (1 - 2 * (value - action).abs()).clamp(min=0).prod(-1)
            return action, confidence
        probs = [F.softmax(x, -1) for x in output.split(list(self.config.action_sizes), dim=-1)]
        best = [p.max(-1) for p in probs]
        action = torch.stack([b.indices for b in best], dim=-1)
        confidence = torch.stack([b.values for b in best], dim=-1).prod(-1)
        return action, confidence

    def _scale(self, target: torch.Tensor) -> torch.Tensor:
        sizes = torch.tensor(self.config.action_sizes, dtype=torch.float32)
        return target.float() / (sizes - 1).clamp(min=1)
