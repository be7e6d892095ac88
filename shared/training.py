"""What the VAE and APN trainers share: their runs count optimiser steps, not passes over the
data, so a small dataset trains as long as a large one (issue 14)."""

from __future__ import annotations

from collections.abc import Iterator

import torch


def minibatches(n: int, batch_size: int, generator: torch.Generator) -> Iterator[torch.Tensor]:
    """Minibatch indices forever: a fresh permutation a pass, the last batch of a pass short."""
    while True:
        order = torch.randperm(n, generator=generator)
        for start in range(0, n, batch_size):
            yield order[start : start + batch_size]


def resolve_device(name: str) -> torch.device:
    """`auto` takes a CUDA device when one is present, the CPU otherwise; asking for `cuda`
    on a machine without one is an error rather than a silent CPU run."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device: {name!r} asked for, but this machine has no CUDA device")
    if device.type not in ("cpu", "cuda"):
        raise ValueError(f"device: {name!r} is not auto, cpu or cuda")
    return device
