"""`lsr eval vfm`: Table I for one model folder (VAE + roadmap), with decoded-image checks."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from services.encoder.checkpoint import decode_latents, encode_images
from services.encoder.model import VAE
from services.planner.build import default_metric, load_model
from services.planner.evaluate import (
    class_distances,
    demonstrated_reach,
    evaluate_interpolation,
    evaluate_plans,
    sample_test_pairs,
    shows_everything,
)
from services.planner.knowing import (
    Calibration,
    MatchError,
    load_calibration,
    match,
    reconstruction_errors,
)
from services.planner.members import interleave
from services.planner.roadmap import Roadmap
from services.planner.versions import roadmap_dir
from services.sim.state_reader import StateReader, load_reader, read_states
from shared.dataset import Dataset, load_dataset
from shared.tasks import get_task


def load_test_images(test_dir: Path | str) -> tuple[np.ndarray, np.ndarray, str]:
    """All images of a test set (both images of every tuple) with their state arrays."""
    data = load_dataset(test_dir)
    return interleave(data.image1, data.image2), interleave(data.state1, data.state2), data.task


def _calibration(model_dir: Path | str, roadmap: Roadmap) -> Calibration | None:
    try:
        return load_calibration(roadmap_dir(model_dir), roadmap)
    except MatchError:
        return None


def run_vfm_eval(
    model_dir: Path | str,
    test_dir: Path | str,
    pairs: int = 1000,
    seed: int = 0,
    max_paths: int = 1000,
    reader_dir: Path | str | None = None,
    train_dir: Path | str | None = None,
) -> tuple[dict[str, Any], dict[str, Any] | None]:
    """Returns the table row and, when training data is at hand, the class-distance analysis."""
    started = time.perf_counter()
    vae, vae_config, roadmap, labels = load_model(model_dir)
    images, states, task_name = load_test_images(test_dir)
    if images.shape[1] != vae_config["model"]["image_size"]:
        raise ValueError(
            f"test images are {images.shape[1]} px, the VAE takes "
            f"{vae_config['model']['image_size']} px"
        )
    z_test, _ = encode_images(vae, images)
    test_pairs = sample_test_pairs(len(images), pairs, seed)
    calibration = _calibration(model_dir, roadmap)

    reader = load_reader(reader_dir) if reader_dir else None
    node_reads = None
    if reader is not None and roadmap.num_nodes:
        node_reads = read_states(reader, decode_latents(vae, roadmap.nodes.astype(np.float32)))
    task = get_task(task_name)
    row: dict[str, Any] = {
        "model": str(model_dir),
        "vae_metric": vae_config["train"]["metric"],
        "roadmap_metric": roadmap.config.metric,
        "nodes": len(roadmap.nodes),
        "edges": len(roadmap.edges),
        "epsilon": roadmap.epsilon,
        "node_purity_mean": float(labels.purity.mean()) if len(labels.purity) else 0.0,
        "pure_nodes": int((labels.purity == 1).sum()),
        "distinct_node_states": len({s.tobytes() for s in labels.states}),
        "distinct_node_views": len({task.view(task.array_to_state(s)) for s in labels.states}),
        "num_views": task.num_views(),
        **evaluate_plans(
            task_name,
            roadmap,
            labels,
            z_test,
            states,
            test_pairs,
            max_paths,
            node_reads,
            calibration,
        ),
    }
    # A state with a part no image shows (the T-shirt's sleeve under its folded half) caps any
    # model; the pairs whose ends show everything measure the method apart from that.
    both_shown = shows_everything(task, states)[test_pairs].all(1)
    if not both_shown.all():
        row["pairs_showing_every_part"] = 100.0 * float(both_shown.mean())
        if both_shown.any():
            shown = evaluate_plans(
                task_name,
                roadmap,
                labels,
                z_test,
                states,
                test_pairs[both_shown],
                max_paths,
                calibration=calibration,
            )
            row["shown_pairs"] = {k: shown[k] for k in ("pairs", "all", "any", "trans")}
    if calibration is not None:
        errors = reconstruction_errors(vae, images, z_test)
        known = np.array([m.known for m in match(roadmap, calibration, z_test, errors)])
        # With refusal on a pair with an unknown end gets no plan: Table I over all pairs
        # counts it as failed; `known_pairs` says how the plans of the others fared.
        both = known[test_pairs].all(1)
        row["known_images"] = 100.0 * float(known.mean())
        row["pairs_known"] = 100.0 * float(both.mean())
        if both.any():
            kept = evaluate_plans(
                task_name,
                roadmap,
                labels,
                z_test,
                states,
                test_pairs[both],
                max_paths,
                calibration=calibration,
            )
            row["known_pairs"] = {k: kept[k] for k in ("pairs", "all", "any", "trans")}
            row["refusal_on"] = {k: kept[k] * float(both.mean()) for k in ("all", "any")}
    if reader is not None:
        row["reader_on_test_renders"] = 100.0 * float(
            (read_states(reader, images) == states).reshape(len(images), -1).all(1).mean()
        )
        row["interpolation"] = _interpolation(
            vae, roadmap, reader, z_test, states, test_pairs, task_name
        )
    analysis = None
    train_dir = train_dir or vae_config["dataset"]["path"]
    if train_dir and Path(train_dir).is_dir():
        train = load_dataset(train_dir)
        row["demonstrated_reach"] = demonstrated_reach(
            train.state1, train.state2, train.a, states, test_pairs
        )
        analysis = _class_analysis(vae, train, default_metric(vae_config))
        row["mean_min_inter_minus_max_intra"] = analysis["mean_min_inter_minus_max_intra"]
        row["classes_separated"] = analysis["classes_separated"]
        row["classes"] = analysis["classes"]
    row["seconds"] = time.perf_counter() - started
    return row, analysis


def _interpolation(
    vae: VAE,
    roadmap: Roadmap,
    reader: StateReader,
    z_test: np.ndarray,
    states: np.ndarray,
    test_pairs: np.ndarray,
    task_name: str,
) -> dict[str, Any]:
    """Straight lines in latent space with as many points as the roadmap's shortest path."""
    nearest = np.asarray(roadmap.nearest_node(z_test)) if roadmap.num_nodes else None
    reads = []
    for i, j in test_pairs:
        paths = (
            roadmap.shortest_paths(int(nearest[i]), int(nearest[j]), max_paths=1)
            if nearest is not None
            else []
        )
        n = len(paths[0]) if paths else 2
        t = np.linspace(0.0, 1.0, n)[:, None]
        line = (1 - t) * z_test[i] + t * z_test[j]
        reads.append(read_states(reader, decode_latents(vae, line.astype(np.float32))))
    return evaluate_interpolation(task_name, reads, states, test_pairs)


def _class_analysis(vae: VAE, data: Dataset, metric: str) -> dict[str, Any]:
    """Classes = distinct true states of the training images."""
    z = interleave(encode_images(vae, data.image1)[0], encode_images(vae, data.image2)[0])
    point_states = interleave(data.state1, data.state2).reshape(len(z), -1)
    _, classes = np.unique(point_states, axis=0, return_inverse=True)
    return class_distances(z, classes.ravel(), metric)
