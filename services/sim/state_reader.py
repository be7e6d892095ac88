"""An image -> state reader: a small CNN that classifies what stands in each cell of a picture.

It is the automatic eye of the evaluation: it tells which state a decoded plan image shows.
Trained on rendered images with known states (mildly blurred at random, since decoded images
are softer than renders), it must read fresh renders at >= 99.5%.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from safetensors.torch import load_file, save_file
from torch import nn
from torch.nn import functional as F
from tqdm import tqdm

from services.encoder.model import to_tensor
from shared.checkpoint import read_config, replace_atomically, seal, weights_file
from shared.dataset import Dataset
from shared.tasks import DEFAULT_TASK, get_task

FORMAT = "lsr-state-reader"
VERSION = 1


@dataclass(frozen=True)
class ReaderConfig:
    task: str = DEFAULT_TASK
    image_size: int = 64
    cells: int = 9  # elements of the task's state array
    values: int = 5  # classes per element: the values start .. start + values - 1
    start: int = -1  # the first value (box stacking: -1 = empty)


class StateReader(nn.Module):
    def __init__(self, config: ReaderConfig) -> None:
        super().__init__()
        self.config = config
        self.features = nn.Sequential(
            nn.Conv2d(3, 32, 3, stride=2, padding=1), nn.SiLU(),
            nn.Conv2d(32, 64, 3, stride=2, padding=1), nn.SiLU(),
            nn.Conv2d(64, 64, 3, stride=2, padding=1), nn.SiLU(),
            nn.AdaptiveAvgPool2d(8), nn.Flatten(),
        )  # fmt: skip
        self.head = nn.Sequential(
            nn.Linear(64 * 8 * 8, 256), nn.SiLU(), nn.Linear(256, config.cells * config.values)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Images in [0, 1] -> logits (B, cells, values)."""
        return self.head(self.features(x)).view(-1, self.config.cells, self.config.values)


def _blur(x: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Random Gaussian blur (sigma 0..1.2 px) on half of the batch."""
    sigma = torch.rand(len(x), generator=generator) * 1.2
    sigma[torch.rand(len(x), generator=generator) < 0.5] = 0
    out = x.clone()
    radius = torch.arange(-2, 3, dtype=x.dtype)
    for i in torch.nonzero(sigma > 0.05).flatten().tolist():
        k = torch.exp(-(radius**2) / (2 * float(sigma[i]) ** 2))
        k = (k / k.sum()).to(x.dtype)
        img = out[i : i + 1].transpose(0, 1)  # (3, 1, H, W): blur channels independently
        img = F.conv2d(F.pad(img, (2, 2, 0, 0), mode="replicate"), k.view(1, 1, 1, 5))
        img = F.conv2d(F.pad(img, (0, 0, 2, 2), mode="replicate"), k.view(1, 1, 5, 1))
        out[i] = img.transpose(0, 1)[0]
    return out


def reader_targets(states: np.ndarray, start: int) -> torch.Tensor:
    """State arrays -> class ids per element (value - start)."""
    return torch.from_numpy(states.reshape(len(states), -1).astype(np.int64) - start)


def train_reader(
    data: Dataset, out_dir: Path | str, epochs: int = 8, seed: int = 0, progress: bool = True
) -> dict[str, Any]:
    torch.manual_seed(seed)
    spec = data.spec.state
    if spec is None:
        raise ValueError(f"{data.task}: the dataset declares no states, there is nothing to read")
    if len(set(spec.counts)) != 1:
        raise ValueError("the state reader needs the same value range for every element")
    config = ReaderConfig(
        task=data.task,
        image_size=data.image_size,
        cells=len(spec.counts),
        values=spec.counts[0],
        start=spec.start,
    )
    model = StateReader(config)
    images = torch.from_numpy(np.concatenate([data.image1, data.image2]))
    targets = reader_targets(np.concatenate([data.state1, data.state2]), config.start)
    optimiser = torch.optim.Adam(model.parameters(), lr=2e-3)
    generator = torch.Generator().manual_seed(seed)
    batch = 128
    steps = epochs * ((len(images) + batch - 1) // batch)
    schedule = torch.optim.lr_scheduler.OneCycleLR(optimiser, max_lr=2e-3, total_steps=steps)
    started = time.perf_counter()
    bar = tqdm(total=steps, unit="step", desc="train state reader", disable=not progress)
    for _ in range(epochs):
        model.train()
        for idx in torch.randperm(len(images), generator=generator).split(batch):
            x = _blur(to_tensor(images[idx]), generator)
            loss = F.cross_entropy(model(x).flatten(0, 1), targets[idx].flatten())
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()
            schedule.step()
            bar.update(1)
            bar.set_postfix(loss=f"{loss.item():.4f}")
    bar.close()
    model.eval()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    weights = {k: v.contiguous() for k, v in model.state_dict().items()}
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "model": asdict(config),
        "train": {
            "epochs": epochs,
            "seed": seed,
            "dataset_seed": data.manifest["seed"],
            "images": len(images),
            "seconds": time.perf_counter() - started,
        },
    }
    text = json.dumps(meta, indent=2) + "\n"
    replace_atomically(out_dir / "reader.safetensors", lambda tmp: save_file(weights, tmp))
    replace_atomically(out_dir / "config.json", lambda tmp: tmp.write_text(text))
    seal(out_dir, ["reader.safetensors", "config.json"])
    return meta


def load_reader(directory: Path | str) -> StateReader:
    meta = read_config(directory, FORMAT, VERSION, "a state reader")
    model = StateReader(ReaderConfig(**meta["model"]))
    model.load_state_dict(load_file(weights_file(directory, "reader.safetensors")))
    return model.eval()


@torch.inference_mode()
def read_states(model: StateReader, images: np.ndarray, batch: int = 500) -> np.ndarray:
    """uint8 images -> state arrays, shaped and typed as the task's spec declares."""
    spec = get_task(model.config.task).spec.state
    assert spec is not None
    out = []
    for start in range(0, len(images), batch):
        x = to_tensor(torch.from_numpy(np.ascontiguousarray(images[start : start + batch])))
        out.append(model(x).argmax(-1).numpy() + model.config.start)
    return np.concatenate(out).reshape(-1, *spec.shape).astype(spec.dtype)
