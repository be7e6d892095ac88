"""Knowing an image: how far its latent lies from the roadmap, against what training showed.

A robot acts on the plans it is given, so an image unlike anything the model was trained on
must be refused rather than mapped to its nearest node. The measure is the distance (the
roadmap's metric) from the image's encoder mean to the nearest roadmap node; the threshold is
a fixed factor times a high quantile of the same distance over the training images, so that it
needs nothing but the training data (tasks defined by their data have no labels).

Measured on the shipped box-stacking model (issue 21's study): training images' distances reach
0.50 (99.9%) and 0.62 (max), unseen ones 0.74; the nearest of eleven kinds of foreign image
(noise, solid frames, inversion, rotation, a third-of-frame shift, occlusion, exposure, the
other task, a box missing or added) lay at 2.34, most at 8 and beyond. Reconstruction error was
no help: the decoder paints a plausible scene for a missing box.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from services.planner.roadmap import Roadmap
from shared.checkpoint import replace_atomically
from shared.plans import Match, UnknownImageError, refused_end

FILE = "match.json"
FORMAT = "lsr-match"
QUANTILE = 0.999
FACTOR = 2.0


class MatchError(ValueError):
    """A calibration that is missing, malformed or does not fit its roadmap."""


@dataclass(frozen=True)
class Calibration:
    """The distance up to which an image counts as known, and what it was computed from."""

    threshold: float  # factor x the quantile of the training images' distances
    quantile: float
    factor: float
    training_quantile: float  # the training images' distance at `quantile`
    training_max: float
    images: int
    metric: str

    def to_json(self) -> dict[str, Any]:
        return {"format": FORMAT, "version": 1, **asdict(self)}


def distances(roadmap: Roadmap, latents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(nearest node, distance to it) for each latent (M, D), in the roadmap's metric."""
    latents = np.asarray(latents, dtype=np.float64).reshape(-1, roadmap.nodes.shape[1])
    nodes = np.atleast_1d(roadmap.nearest_node(latents))
    gaps = latents - roadmap.nodes[nodes].astype(np.float64)
    order = {"l1": 1, "l2": 2, "inf": np.inf}[roadmap.config.metric]
    return nodes, np.linalg.norm(gaps, ord=order, axis=1)


def calibrate(
    roadmap: Roadmap, latents: np.ndarray, quantile: float = QUANTILE, factor: float = FACTOR
) -> Calibration:
    """The threshold from the training images' latents (every image of the training tuples)."""
    if len(latents) == 0:
        raise MatchError("calibration needs at least one training image")
    _, gaps = distances(roadmap, latents)
    at = float(np.quantile(gaps, quantile))
    return Calibration(
        threshold=factor * at,
        quantile=quantile,
        factor=factor,
        training_quantile=at,
        training_max=float(gaps.max()),
        images=len(gaps),
        metric=roadmap.config.metric,
    )


def match(roadmap: Roadmap, calibration: Calibration, latents: np.ndarray) -> list[Match]:
    nodes, gaps = distances(roadmap, latents)
    scores = gaps / calibration.threshold if calibration.threshold > 0 else np.inf * gaps
    return [
        Match(known=bool(s <= 1.0), score=float(s), node=int(n))
        for n, s in zip(nodes, scores, strict=True)
    ]


def check_ends(
    roadmap: Roadmap, calibration: Calibration, z_start: np.ndarray, z_goal: np.ndarray
) -> dict[str, Match]:
    """Both ends' matches; UnknownImageError naming the first end that is not known."""
    start, goal = match(roadmap, calibration, np.stack([z_start, z_goal]))
    matched = {"start": start, "goal": goal}
    end = refused_end(matched)
    if end is not None:
        raise UnknownImageError(end, refusal(end, matched[end], calibration), matched)
    return matched


def save_calibration(calibration: Calibration, roadmap_dir: Path | str) -> Path:
    path = Path(roadmap_dir) / FILE
    text = json.dumps(calibration.to_json(), indent=2, allow_nan=False) + "\n"
    replace_atomically(path, lambda tmp: tmp.write_text(text))
    return path


def load_calibration(roadmap_dir: Path | str, roadmap: Roadmap) -> Calibration:
    """The roadmap's calibration; MatchError names what is missing or does not fit."""
    path = Path(roadmap_dir) / FILE
    if not path.is_file():
        raise MatchError(
            f"{path}: missing; calibrate the model with "
            f"`lsr calibrate --model <model> --data <its training data>`"
        )
    try:
        document = json.loads(path.read_text())
        if document.get("format") != FORMAT or document.get("version") != 1:
            raise MatchError(f"{path}: expected format {FORMAT!r} version 1")
        fields = {k: document[k] for k in Calibration.__dataclass_fields__}
        calibration = Calibration(**fields)
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise MatchError(f"{path}: not a calibration ({exc})") from exc
    if calibration.metric != roadmap.config.metric:
        raise MatchError(
            f"{path}: calibrated in {calibration.metric}, the roadmap measures in "
            f"{roadmap.config.metric}"
        )
    if not (np.isfinite(calibration.threshold) and calibration.threshold > 0):
        raise MatchError(f"{path}: threshold must be a positive number")
    return calibration


def refusal(end: str, found: Match, calibration: Calibration) -> str:
    """The reason a plan is refused, naming the end (`start` or `goal`) in plain words."""
    return (
        f"the {end} image is unlike anything this model knows: its latent lies far from every "
        f"roadmap region (score {found.score:.2f}; known up to 1, which is {calibration.factor:g} "
        f"times the distance {100 * calibration.quantile:g}% of training images stay within)"
    )
