"""`lsr build-roadmap`: encode a training set with a VAE and build its Latent Space Roadmap."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from services.encoder.checkpoint import encode_images, load_vae, read_vae_config
from services.encoder.model import VAE
from services.planner.evaluate import NodeLabels, label_nodes
from services.planner.knowing import FILE as MATCH_FILE
from services.planner.knowing import Calibration, calibrate, reconstruction_errors, save_calibration
from services.planner.roadmap import ARRAYS_NAME, JSON_NAME, Roadmap, RoadmapConfig, build_roadmap
from shared.checkpoint import seal
from shared.dataset import Dataset, load_dataset
from shared.tasks import get_task

LABELS = "labels.json"


def default_metric(vae_config: dict[str, Any]) -> str:
    """The roadmap uses the metric the VAE was shaped with (L1 for the baseline)."""
    metric = vae_config["train"]["metric"]
    return "l1" if metric == "none" else metric


def encode_pairs(model: VAE, data: Dataset) -> tuple[np.ndarray, np.ndarray]:
    """The encoder means of image1 and image2 of every tuple."""
    if model.config.image_size != data.image_size:
        raise ValueError(
            f"the VAE takes {model.config.image_size} px images, "
            f"the dataset has {data.image_size} px"
        )
    return encode_images(model, data.image1)[0], encode_images(model, data.image2)[0]


def calibrate_and_seal(
    model: VAE,
    data: Dataset,
    roadmap: Roadmap,
    mu1: np.ndarray,
    mu2: np.ndarray,
    roadmap_dir: Path | str,
) -> Calibration:
    """What the roadmap knows, from every training image (mu1, mu2: the latents of image1 and
    image2), written beside the roadmap and sealed with it: build-roadmap and lsr calibrate."""
    pairs = ((data.image1, mu1), (data.image2, mu2))
    errors = np.concatenate([reconstruction_errors(model, x, mu) for x, mu in pairs])
    calibration = calibrate(roadmap, np.concatenate([mu1, mu2]), errors)
    save_calibration(calibration, roadmap_dir)
    seal(roadmap_dir, [ARRAYS_NAME, JSON_NAME, MATCH_FILE])
    return calibration


def interleave(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Rows in the roadmap's point order: first[0], second[0], first[1], ..."""
    return np.stack([first, second], axis=1).reshape(-1, *first.shape[1:])


def build_from_dataset(
    vae_dir: Path | str, data_dir: Path | str, config: RoadmapConfig, out_dir: Path | str
) -> dict[str, Any]:
    started = time.perf_counter()
    data = load_dataset(data_dir)
    model, _ = load_vae(vae_dir)
    mu1, mu2 = encode_pairs(model, data)
    encoded = time.perf_counter()
    roadmap = build_roadmap(mu1, mu2, data.a, config)
    built = time.perf_counter()
    roadmap.save(out_dir)
    calibration = calibrate_and_seal(model, data, roadmap, mu1, mu2, out_dir)
    purity: dict[str, Any] = {}
    if data.spec.state is not None:  # node labels need the states the data declares
        labels = label_nodes(
            roadmap.point_node, interleave(data.state1, data.state2), len(roadmap.nodes)
        )
        (Path(out_dir) / LABELS).write_text(json.dumps(labels.to_json(get_task(data.task))) + "\n")
        purity = {
            "mean_purity": float(labels.purity.mean()) if len(labels.purity) else 0.0,
            "pure_nodes": int((labels.purity == 1).sum()),
        }
    return {
        "nodes": len(roadmap.nodes),
        "edges": len(roadmap.edges),
        "epsilon": roadmap.epsilon,
        **purity,
        "match_threshold": calibration.threshold,
        "encode_seconds": encoded - started,
        "build_seconds": built - encoded,
        **{k: v for k, v in roadmap.stats.items() if not isinstance(v, dict)},
    }


def calibrate_model(model_dir: Path | str, data_dir: Path | str) -> dict[str, Any]:
    """Calibrate (or re-calibrate) a model's roadmap on its training data: `lsr calibrate`."""
    model_dir = Path(model_dir)
    data = load_dataset(data_dir)
    task = read_vae_config(model_dir / "vae")["dataset"]["task"]
    if data.task != task:
        raise ValueError(f"{data_dir} holds {data.task!r} data, the model plans {task!r}")
    roadmap = Roadmap.load(model_dir / "roadmap")
    model, _ = load_vae(model_dir / "vae")
    mu1, mu2 = encode_pairs(model, data)
    roadmap_dir = model_dir / "roadmap"
    return calibrate_and_seal(model, data, roadmap, mu1, mu2, roadmap_dir).to_json()


def load_labels(roadmap_dir: Path | str, task_name: str) -> NodeLabels:
    path = Path(roadmap_dir) / LABELS
    if not path.is_file():
        raise ValueError(f"{roadmap_dir}: no {LABELS}; rebuild with lsr build-roadmap")
    return NodeLabels.from_json(get_task(task_name), json.loads(path.read_text()))


def load_model(model_dir: Path | str) -> tuple[Any, dict[str, Any], Roadmap, NodeLabels]:
    """A model folder: vae/ and roadmap/ side by side."""
    model_dir = Path(model_dir)
    vae, vae_config = load_vae(model_dir / "vae")
    roadmap = Roadmap.load(model_dir / "roadmap")
    labels = load_labels(model_dir / "roadmap", vae_config["dataset"]["task"])
    return vae, vae_config, roadmap, labels
