"""The VAE: a small residual conv encoder/decoder, sized from the image size."""

from __future__ import annotations

import itertools
import math
from dataclasses import asdict, dataclass

import torch
from torch import nn
from torch.nn import functional as F


@dataclass(frozen=True)
class VAEConfig:
    image_size: int = 64
    latent_dim: int = 64
    base_channels: int = 32
    max_channels: int = 128

    def __post_init__(self) -> None:
        levels = math.log2(self.image_size / 4)
        if self.image_size < 16 or levels != int(levels):
            raise ValueError(f"image_size must be a power of two >= 16, got {self.image_size}")

    @property
    def channels(self) -> list[int]:
        """Channels after each stride-2 block, from the image down to 4x4."""
        n = int(math.log2(self.image_size / 4))
        return [min(self.base_channels * 2**i, self.max_channels) for i in range(n)]

    def to_dict(self) -> dict:
        return asdict(self)


class Residual(nn.Module):
    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.silu(x + self.conv(x))


class VAE(nn.Module):
    def __init__(self, config: VAEConfig) -> None:
        super().__init__()
        self.config = config
        chans = config.channels
        down: list[nn.Module] = []
        c_in = 3
        for c in chans:
            down += [nn.Conv2d(c_in, c, 4, stride=2, padding=1), nn.SiLU(), Residual(c)]
            c_in = c
        self.encoder = nn.Sequential(*down, nn.Flatten())
        flat = chans[-1] * 4 * 4
        self.to_mu = nn.Linear(flat, config.latent_dim)
        self.to_logvar = nn.Linear(flat, config.latent_dim)

        self.from_latent = nn.Linear(config.latent_dim, flat)
        up: list[nn.Module] = []
        rev = chans[::-1]
        for c, c_out in itertools.pairwise(rev):
            up += [nn.ConvTranspose2d(c, c_out, 4, stride=2, padding=1), nn.SiLU(), Residual(c_out)]
        up += [nn.ConvTranspose2d(rev[-1], 3, 4, stride=2, padding=1)]
        self.decoder = nn.Sequential(*up)

    def encode(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """x: float images in [0, 1], (B, 3, H, W) -> mean and log-variance of q(z|x)."""
        h = self.encoder(x)
        return self.to_mu(h), self.to_logvar(h).clamp(-12.0, 8.0)

    def decode(self, z: torch.Tensor, channels_last: bool = False) -> torch.Tensor:
        """`channels_last`: a fifth faster on CPU; inference only, so that training keeps the
        arithmetic its models were measured with."""
        c = self.config.channels[-1]
        h = self.from_latent(z).view(-1, c, 4, 4)
        if channels_last:
            h = h.contiguous(memory_format=torch.channels_last)
        return torch.sigmoid(self.decoder(h))

    def forward(
        self, x: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        mu, logvar = self.encode(x)
        z = mu + torch.randn_like(mu) * torch.exp(0.5 * logvar)
        return self.decode(z), mu, logvar, z


def to_tensor(images_uint8: torch.Tensor) -> torch.Tensor:
    """(B, H, W, 3) uint8 -> (B, 3, H, W) float in [0, 1]."""
    return images_uint8.permute(0, 3, 1, 2).float().div_(255.0)


def to_uint8(images: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) float in [0, 1] -> (B, H, W, 3) uint8."""
    return images.clamp(0, 1).mul(255).round().to(torch.uint8).permute(0, 2, 3, 1)
