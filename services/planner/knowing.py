"""Knowing an image: is it like the training images, by where its latent lies and by how well
the model redraws it?

A robot acts on the plans it is given, so an image unlike anything the model was trained on
must be refused rather than mapped to its nearest node. Two terms, each over a threshold that
is a fixed factor times a high quantile of the same term over the training images (so that it
needs nothing but the training data; tasks defined by their data have no labels):
- the distance (the roadmap's metric) from the image's encoder mean to the nearest node;
- the reconstruction error: mean squared error of the decoded mean against the image.
The score is the larger of the two ratios; an image is known while it is at most 1.

Measured (issue 21): on the box model the distance alone refused every foreign kind tried,
where reconstruction let a missing or an added box through (the decoder paints a plausible
scene); on the cloth model the distance let 41-44% of box-stacking images through (its 16
nodes lie far apart) and reconstruction refused them all.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from services.encoder.checkpoint import decode_latents
from services.encoder.model import VAE
from services.planner.regions import metric_p
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
    """How far and how badly redrawn an image may be and still count as known."""

    threshold: float  # distance: factor x the quantile of the training images' distances
    recon_threshold: float  # reconstruction error, likewise
    quantile: float
    factor: float
    training_quantile: float  # the training images' distance at `quantile`
    training_max: float
    recon_quantile: float  # the training images' reconstruction error at `quantile`
    recon_max: float
    images: int
    metric: str

    def to_json(self) -> dict[str, Any]:
        return {"format": FORMAT, "version": 2, **asdict(self)}


def reconstruction_errors(vae: VAE, images: np.ndarray, latents: np.ndarray) -> np.ndarray:
    """Mean squared error per image (pixels in [0, 1]) of the decoded encoder means."""
    errors = np.empty(len(images), np.float64)
    for start in range(0, len(images), 500):
        part = slice(start, start + 500)
        drawn = decode_latents(vae, np.asarray(latents[part], np.float32)).astype(np.float32)
        gaps = (drawn - images[part].astype(np.float32)) / 255.0
        errors[part] = (gaps**2).reshape(len(drawn), -1).mean(1)
    return errors


def distances(roadmap: Roadmap, latents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(nearest node, distance to it) for each latent (M, D), in the roadmap's metric."""
    latents = np.asarray(latents, dtype=np.float64).reshape(-1, roadmap.nodes.shape[1])
    nodes = np.atleast_1d(roadmap.nearest_node(latents))
    gaps = latents - roadmap.nodes[nodes].astype(np.float64)
    return nodes, np.linalg.norm(gaps, ord=metric_p(roadmap.config.metric), axis=1)


def calibrate(
    roadmap: Roadmap,
    latents: np.ndarray,
    errors: np.ndarray,
    quantile: float = QUANTILE,
    factor: float = FACTOR,
) -> Calibration:
    """The thresholds from every training image's latent and reconstruction error."""
    if len(latents) == 0 or len(errors) != len(latents):
        raise MatchError(
            f"calibration needs a latent and an error per training image, got {len(latents)} "
            f"latents and {len(errors)} errors"
        )
    _, gaps = distances(roadmap, latents)
    at, recon_at = (float(np.quantile(x, quantile)) for x in (gaps, errors))
    return Calibration(
        threshold=factor * at,
        recon_threshold=factor * recon_at,
        quantile=quantile,
        factor=factor,
        training_quantile=at,
        training_max=float(gaps.max()),
        recon_quantile=recon_at,
        recon_max=float(np.max(errors)),
        images=len(gaps),
        metric=roadmap.config.metric,
    )


def match(
    roadmap: Roadmap, calibration: Calibration, latents: np.ndarray, errors: np.ndarray
) -> list[Match]:
    nodes, gaps = distances(roadmap, latents)
    scores = np.maximum(
        gaps / calibration.threshold, np.asarray(errors) / calibration.recon_threshold
    )
    return [
        Match(known=bool(s <= 1.0), score=float(s), node=int(n))
        for n, s in zip(nodes, scores, strict=True)
    ]


def check_ends(
    roadmap: Roadmap,
    calibration: Calibration,
    z_start: np.ndarray,
    z_goal: np.ndarray,
    errors: np.ndarray,
) -> dict[str, Match]:
    """Both ends' matches; UnknownImageError naming the first end that is not known."""
    start, goal = match(roadmap, calibration, np.stack([z_start, z_goal]), errors)
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
        if document.get("format") != FORMAT or document.get("version") != 2:
            raise MatchError(
                f"{path}: expected format {FORMAT!r} version 2; calibrate the model again "
                "with `lsr calibrate`"
            )
        fields = {k: document[k] for k in Calibration.__dataclass_fields__}
        calibration = Calibration(**fields)
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise MatchError(f"{path}: not a calibration ({exc})") from exc
    if calibration.metric != roadmap.config.metric:
        raise MatchError(
            f"{path}: calibrated in {calibration.metric}, the roadmap measures in "
            f"{roadmap.config.metric}"
        )
    for name in ("threshold", "recon_threshold"):
        value = getattr(calibration, name)
        if not (isinstance(value, int | float) and np.isfinite(value) and value > 0):
            raise MatchError(f"{path}: {name} must be a positive number")
    return calibration


def refusal(end: str, found: Match, calibration: Calibration) -> str:
    """The reason a plan is refused, naming the end (`start` or `goal`) in plain words."""
    return (
        f"the {end} image is unlike anything this model knows: its latent lies far from every "
        f"roadmap region or the model cannot redraw it (score {found.score:.2f}; known up to 1, "
        f"which is {calibration.factor:g} times what {100 * calibration.quantile:g}% of "
        "training images stay within)"
    )
