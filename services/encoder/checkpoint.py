"""VAE checkpoints: safetensors weights plus a JSON config, never pickle."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from services.encoder.model import VAE, VAEConfig, to_tensor, to_uint8
from shared.checkpoint import read_config, replace_atomically, seal, weights_file

FORMAT = "lsr-vae"
VERSION = 1
WEIGHTS = "vae.safetensors"
CONFIG = "config.json"


def save_vae(model: VAE, directory: Path | str, meta: dict[str, Any]) -> None:
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    tensors = {k: v.detach().contiguous().cpu() for k, v in model.state_dict().items()}
    replace_atomically(directory / WEIGHTS, lambda tmp: save_file(tensors, tmp))
    config = {"format": FORMAT, "version": VERSION, "model": model.config.to_dict(), **meta}
    text = json.dumps(config, indent=2, sort_keys=True) + "\n"
    replace_atomically(directory / CONFIG, lambda tmp: tmp.write_text(text))
    seal(directory, [WEIGHTS, CONFIG])


def read_vae_config(directory: Path | str) -> dict[str, Any]:
    return read_config(directory, FORMAT, VERSION, "a VAE model")


def load_vae(directory: Path | str) -> tuple[VAE, dict[str, Any]]:
    config = read_vae_config(directory)
    weights = weights_file(directory, WEIGHTS)
    model = VAE(VAEConfig(**config["model"]))
    state = {k: v.float() for k, v in load_file(weights).items()}
    model.load_state_dict(state)
    model.eval()
    return model, config


@torch.inference_mode()
def encode_images(
    model: VAE, images: np.ndarray, batch_size: int = 500
) -> tuple[np.ndarray, np.ndarray]:
    """uint8 (N, H, W, 3) -> encoder means and log-variances, float32 (N, latent_dim)."""
    mus, logvars = [], []
    device = next(model.parameters()).device
    for start in range(0, len(images), batch_size):
        x = to_tensor(torch.from_numpy(np.ascontiguousarray(images[start : start + batch_size])))
        x = x.to(device).contiguous(memory_format=torch.channels_last)
        mu, logvar = model.encode(x)
        mus.append(mu.cpu().numpy())
        logvars.append(logvar.cpu().numpy())
    return np.concatenate(mus), np.concatenate(logvars)


@torch.inference_mode()
def decode_latents(model: VAE, z: np.ndarray, batch_size: int = 500) -> np.ndarray:
    """float (N, latent_dim) -> uint8 images (N, H, W, 3)."""
    out = []
    for start in range(0, len(z), batch_size):
        out.append(
            to_uint8(
                model.decode(torch.from_numpy(z[start : start + batch_size]).float(), True)
            ).numpy()
        )
    return np.concatenate(out)
