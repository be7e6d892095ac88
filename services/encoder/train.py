"""Training of the action-VAE (paper eq. 2-4): two VAE terms plus gamma times the action term."""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from services.encoder.checkpoint import encode_images, load_vae, save_vae
from services.encoder.model import VAE, VAEConfig, to_tensor
from shared.appearance import manifest_appearance
from shared.dataset import Dataset, load_dataset
from shared.tasks import get_task
from shared.tasks.base import Task, TaskError
from shared.training import minibatches, resolve_device

Metric = Literal["l1", "l2", "inf", "none"]
METRIC_P = {"l1": 1.0, "l2": 2.0, "inf": math.inf}


# Optimiser steps of the default schedule. Steps, not epochs: a small dataset needs as many
# updates as a large one to shape its latent space (1000 tuples trained 30 epochs = 480 steps
# left 23 impure nodes; the shipped box model had 2370). See docs/tasks/box-stacking.md, "Data
# efficiency".
DEFAULT_STEPS = 2400


@dataclass(frozen=True)
class TrainConfig:
    metric: Metric = "l1"
    dm: float | None = None  # None: the paper's value for the task and metric
    steps: int = DEFAULT_STEPS
    epochs: int | None = None  # when set, overrides steps: epochs x ceil(pairs / batch_size)
    batch_size: int = 64  # pairs per step: 2x images
    lr: float = 1e-3
    lr_drop: float = 2 / 3  # lr / 10 after this fraction of the steps (epoch 20 of 30)
    # Gradient-norm clipping. The loss sums squared errors over pixels, so norms run to
    # thousands while beta and gamma ramp up (1000 box tuples: about 1 step in 10 clipped, most
    # in the first third; log.jsonl counts them). Without it one spike at lr 1e-3 once blew up a
    # cloth run (KL 1.9e8); float("inf") trains as the shipped models did.
    clip_grad_norm: float = 1000.0
    log_every: int = 100  # steps between log.jsonl records (and one at the end)
    beta_max: float = 1.0  # beta rises linearly from 0 over the first half of the run
    gamma_start: float = 1.0
    gamma_end: float = 3.0  # gamma rises linearly over the run
    action_weight: float = 40.0  # constant factor on the action term, as in the reference
    latent_dim: int = 64
    seed: int = 0
    threads: int = 2
    device: str = "auto"  # auto: a CUDA device when present, else the CPU
    monitor_pairs: int = 500  # pairs encoded at each log record to log latent distances
    # The reference applies the action term to reparameterised samples. With a collapsed
    # posterior, sample noise alone can exceed d_m (L2: ~11 in 64-D), so "mean" is offered too.
    action_on: Literal["sample", "mean"] = "sample"
    # The encoder sees each image under a freshly drawn look (`augment`) and the decoder is
    # asked for the recorded one, so that a state's looks land together (issue 50).
    augment: bool = False

    def __post_init__(self) -> None:
        if self.metric not in ("l1", "l2", "inf", "none"):
            raise ValueError(f"metric must be l1, l2, inf or none, got {self.metric!r}")
        for name in ("steps", "batch_size", "log_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        if self.epochs is not None and self.epochs < 1:
            raise ValueError(f"epochs must be at least 1, got {self.epochs}")
        if not 0.0 <= self.lr_drop <= 1.0:
            raise ValueError(f"lr_drop must be a fraction in [0, 1], got {self.lr_drop}")
        if not self.clip_grad_norm > 0:
            raise ValueError(f"clip_grad_norm must be positive, got {self.clip_grad_norm}")
        if self.action_on not in ("sample", "mean"):
            raise ValueError(f"action_on must be sample or mean, got {self.action_on!r}")
        if self.dm is not None and self.dm <= 0:
            raise ValueError(f"dm must be positive, got {self.dm}")

    def total_steps(self, pairs: int) -> int:
        """Steps of the run on a dataset of `pairs` tuples."""
        if self.epochs is None:
            return self.steps
        return self.epochs * math.ceil(pairs / self.batch_size)

    def d_m(self, task: str | None = None) -> float:
        """The given d_m, else the task's own (`Task.d_m`: the paper's; a task the paper did
        not study, or none named, the base values)."""
        if self.metric == "none":
            return 0.0
        if self.dm is not None:
            return self.dm
        try:
            values = Task.d_m if task is None else get_task(task).d_m
        except TaskError:
            values = Task.d_m
        return values[self.metric]


def latent_distance(z1: torch.Tensor | np.ndarray, z2: torch.Tensor | np.ndarray, metric: str):
    """||z1 - z2||_p along the last axis, for torch tensors or numpy arrays."""
    p = METRIC_P[metric]
    if isinstance(z1, torch.Tensor):
        return torch.linalg.vector_norm(z1 - z2, ord=p, dim=-1)
    return np.linalg.norm(np.asarray(z1) - np.asarray(z2), ord=p, axis=-1)


def action_term(z1: torch.Tensor, z2: torch.Tensor, a: torch.Tensor, metric: str, dm: float):
    """Paper eq. 3: pull no-action pairs together, push action pairs at least d_m apart."""
    d = latent_distance(z1, z2, metric)
    return torch.where(a > 0, torch.relu(dm - d), d).mean()


def schedules(cfg: TrainConfig, progress: float) -> tuple[float, float]:
    """beta and gamma at a fraction `progress` in [0, 1] of the run."""
    beta = cfg.beta_max * min(1.0, progress / 0.5)
    gamma = (
        0.0
        if cfg.metric == "none"
        else cfg.gamma_start + (cfg.gamma_end - cfg.gamma_start) * progress
    )
    return beta, gamma


def vae_terms(
    model: VAE, x: torch.Tensor, target: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-image summed squared error (against `target`, else `x`), KL to N(0, I), the
    reparameterised sample and the mean."""
    recon, mu, logvar, z = model(x)
    sse = (recon - (x if target is None else target)).pow(2).flatten(1).sum(1)
    kl = 0.5 * (mu.pow(2) + logvar.exp() - 1.0 - logvar).sum(1)
    return sse, kl, z, mu


# A drawn look, as a cell drifts (shared/appearance.py's `camera` ranges, doubled and more):
EXPOSURE = 0.25  # the whole image x U(1 - r, 1 + r)
BALANCE = 0.1  # each channel x U(1 - r, 1 + r)
GRADIENT = 0.15  # a light from one side: the gain runs from 1 - g to 1 + g across the image
NOISE = 0.02  # Gaussian noise, sigma up to this (full scale)
SHIFT = 2  # pixels each way, edges repeated: what registration leaves


def augment(x: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """(B, 3, H, W) images in [0, 1] under a drawn look each: exposure, white balance, a
    light's gradient, sensor noise and a small shift (as DrQ and RAD augment for control)."""
    b, _, h, w = x.shape

    def draw(*shape: int) -> torch.Tensor:  # U(-1, 1), on the CPU generator, then x's device
        return (torch.rand(*shape, generator=generator) * 2 - 1).to(x.device)

    gain = (1 + EXPOSURE * draw(b, 1, 1, 1)) * (1 + BALANCE * draw(b, 3, 1, 1))
    angle = math.pi * draw(b, 1, 1, 1)
    ys = torch.linspace(-1, 1, h, device=x.device)[:, None]
    xs = torch.linspace(-1, 1, w, device=x.device)[None, :]
    ramp = (torch.cos(angle) * xs + torch.sin(angle) * ys).clamp(-1, 1)
    gain = gain * (1 + GRADIENT * draw(b, 1, 1, 1).abs() * ramp)
    sigma = NOISE * draw(b, 1, 1, 1).abs()
    noise = torch.randn(x.shape, generator=generator).to(x.device) * sigma
    looked = F.pad(x * gain + noise, (SHIFT,) * 4, mode="replicate")
    dx, dy = (torch.randint(0, 2 * SHIFT + 1, (b,), generator=generator) for _ in range(2))
    rows = (dy[:, None] + torch.arange(h))[:, None, :, None].to(x.device)
    cols = (dx[:, None] + torch.arange(w))[:, None, None, :].to(x.device)
    every = torch.arange(b, device=x.device)[:, None, None, None]
    channels = torch.arange(x.shape[1], device=x.device)[None, :, None, None]
    return looked[every, channels, rows, cols].clamp(0, 1)  # each image's own window


def latent_gap(mu1: np.ndarray, mu2: np.ndarray, a: np.ndarray, metric: str) -> dict[str, float]:
    """Distances of encoder means: the action term wants max(no-action) < min(action)."""
    m = metric if metric != "none" else "l1"
    d = latent_distance(mu1, mu2, m)
    out: dict[str, float] = {}
    if (a == 0).any():
        out |= {"noaction_mean": float(d[a == 0].mean()), "noaction_max": float(d[a == 0].max())}
    if (a == 1).any():
        out |= {"action_mean": float(d[a == 1].mean()), "action_min": float(d[a == 1].min())}
    if len(out) == 4:
        out["gap"] = out["action_min"] - out["noaction_max"]
    return out


def dm_from_baseline(baseline_dir: Path | str, data: Dataset, metric: str) -> float:
    """The paper's rule for d_m: mean action-pair distance of encoder means under VAE-b."""
    model, _ = load_vae(baseline_dir)
    act = data.a == 1
    mu1, _ = encode_images(model, data.image1[act])
    mu2, _ = encode_images(model, data.image2[act])
    return float(latent_distance(mu1, mu2, metric).mean())


def train_vae(
    data_dir: Path | str,
    out_dir: Path | str,
    cfg: TrainConfig,
    progress: bool = True,
    extra_meta: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Train, write weights + config + log.jsonl to `out_dir`, return the final record."""
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    data = load_dataset(data_dir)
    d_m = cfg.d_m(data.task)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    model = VAE(VAEConfig(image_size=data.image_size, latent_dim=cfg.latent_dim))
    device = resolve_device(cfg.device)
    model = model.to(device, memory_format=torch.channels_last)
    optimiser = torch.optim.Adam(model.parameters(), lr=cfg.lr)

    images1, images2 = torch.from_numpy(data.image1), torch.from_numpy(data.image2)
    a_all = torch.from_numpy(data.a.astype(np.float32))
    n = len(data)
    total_steps = cfg.total_steps(n)
    drop_step = round(cfg.lr_drop * total_steps)
    monitor = np.random.default_rng(cfg.seed).permutation(n)[: cfg.monitor_pairs]
    batches = minibatches(n, cfg.batch_size, torch.Generator().manual_seed(cfg.seed))
    looks = torch.Generator().manual_seed(cfg.seed + 1)  # augment's draws
    log_path = out_dir / "log.jsonl"
    log_path.write_text("")
    started = time.perf_counter()
    record: dict[str, Any] = {}
    sums = dict.fromkeys(("loss", "recon", "kl", "action"), 0.0)
    seen = 0
    grad_norm_max = 0.0
    clipped = 0
    bar = tqdm(total=total_steps, unit="step", desc=f"train vae-{cfg.metric}", disable=not progress)
    for step in range(total_steps):
        model.train()
        lr = cfg.lr if step < drop_step else cfg.lr / 10
        for group in optimiser.param_groups:
            group["lr"] = lr
        idx = next(batches)
        b = len(idx)
        beta, gamma = schedules(cfg, step / total_steps)
        x = to_tensor(torch.cat([images1[idx], images2[idx]]).to(device))
        seen_x = augment(x, looks) if cfg.augment else x
        sse, kl, z, mu = vae_terms(
            model, seen_x.contiguous(memory_format=torch.channels_last), target=x
        )
        if cfg.action_on == "mean":
            z = mu
        recon, kl_mean = sse.mean(), kl.mean()
        act = (
            action_term(z[:b], z[b:], a_all[idx].to(device), cfg.metric, d_m)
            if cfg.metric != "none"
            else torch.zeros((), device=device)
        )
        loss = recon + beta * kl_mean + gamma * cfg.action_weight * act
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        norm = float(torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.clip_grad_norm))
        grad_norm_max = max(grad_norm_max, norm)
        clipped += norm > cfg.clip_grad_norm
        optimiser.step()
        for key, value in (("loss", loss), ("recon", recon), ("kl", kl_mean), ("action", act)):
            sums[key] += value.item() * b
        seen += b
        bar.update(1)
        bar.set_postfix(loss=f"{loss.item():.1f}")
        if (step + 1) % cfg.log_every and step + 1 != total_steps:
            continue
        model.eval()
        mu1, _ = encode_images(model, data.image1[monitor])
        mu2, _ = encode_images(model, data.image2[monitor])
        record = {
            "step": step + 1,
            "epoch": round((step + 1) * cfg.batch_size / n, 3),
            **{k: v / seen for k, v in sums.items()},
            "beta": beta,
            "gamma": gamma,
            "lr": lr,
            "grad_norm_max": grad_norm_max,
            "clipped_steps": clipped,
            "seconds": time.perf_counter() - started,
            **latent_gap(mu1, mu2, data.a[monitor], cfg.metric),
        }
        with log_path.open("a") as log:
            log.write(json.dumps(record) + "\n")
        sums = dict.fromkeys(sums, 0.0)
        seen = 0
        grad_norm_max = 0.0
    bar.close()
    meta = {
        "train": asdict(cfg) | {"d_m": d_m, "total_steps": total_steps, "ran_on": str(device)},
        "dataset": {
            "path": str(data_dir),
            **{k: data.manifest[k] for k in ("task", "seed", "image_size", "counts")},
            "appearance": manifest_appearance(data.manifest),  # what the model expects to see
            "spec": data.spec.to_json(),  # serving a task defined by its data needs it
            "markers": data.manifest.get("markers"),  # and its table's markers, if any
        },
        "train_seconds": time.perf_counter() - started,
        "final": record,
        **(extra_meta or {}),
    }
    save_vae(model, out_dir, meta)
    return record
