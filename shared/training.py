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
