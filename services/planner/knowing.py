"""Knowing an image: is it like the training images, by where its latent lies and by how well
the model redraws it?

A robot acts on the plans it is given, so an image unlike anything the model was trained on
must be refused rather than mapped to its nearest node. Three terms, each over a threshold that
is a fixed factor times a high quantile of the same term over the training images (so that it
needs nothing but the training data; tasks defined by their data have no labels):
- the distance (the roadmap's metric) from the image's encoder mean to the node it matches
  (`Roadmap.nearest_node`), against that node's own training images: regions differ tenfold
  in spread (the cloth model: 0.34 to 3.5), so one threshold for all let a rotated, fully
  folded cloth (a tight region) through;
- the reconstruction error of the decoded mean over the whole image, the drawing scaled to the
  image's exposure first (`errors_of`);
- over its worst quarter-frame patch: a covered half, an upside-down shirt or a shifted
  frame is wrong in one place, which a whole-image mean dilutes into camera noise;
- and the edges the drawing has that the image lacks, in its worst patch (`_missing_edges`):
  a cover of the table's own colour is close in every pixel to a drawing of thin grid lines
  and a rope, but it has no edges where every real scene does.
The score is the largest of the four ratios; an image is known while it is at most 1.

Measured (issue 21, `benchmarks/bench_knowing.py`): the distance alone refused every foreign
kind tried on the box model, where reconstruction let a missing or an added box through (the
decoder paints a plausible scene); on the cloth model a single distance threshold let 41-44% of
box-stacking images through and reconstruction refused them all.
"""

from __future__ import annotations

import json
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from services.encoder.checkpoint import decode_latents
from services.encoder.model import VAE, to_tensor, to_uint8
from services.planner.places import Places
from services.planner.regions import metric_p
from services.planner.roadmap import Roadmap, pair_distances
from shared.checkpoint import replace_atomically
from shared.plans import Match, UnknownImageError, refused_end

FILE = "match.json"
FORMAT = "lsr-match"
VERSION = 5  # 4: the whole-image error after fitting the drawing's exposure; 5: edges
ERRORS = ("whole image", "worst patch", "missing edges")  # what `errors_of` measures, in order
QUANTILE = 0.999
FACTOR = 2.0
EXPOSURE = (0.87, 1.15)  # a drawing's fitted gain: a camera's exposure, within 0.2 stops
PATCHES = 4  # a patch is this fraction of the frame's side, moved by half a patch
# Added to an image patch's mean edge strength (|dx| + |dy| of the blurred grey, [0, 1] a
# pixel): about 2.5 grey levels a pixel, so that a flat patch's ratio stays finite and a flat
# drawing's (a bare table) small. The one value tried; not tuned.
EDGE_FLOOR = 0.01
BATCH = 250  # images a pass: small enough to stay in the cache
_THREADS = threading.Lock()  # look_many switches torch's thread count
# A node's own distance quantile needs this many training images; with fewer (a few hundred
# tuples: 11-37 a node) the 0.999 quantile is the sample's maximum, and 0.6-0.7% of unseen
# images of the node's own state lay past twice it (cloth, T-shirt at 300 tuples, issue 47).
# Such a node takes its median distance times the pooled 0.999 quantile of distance / median
# (its own scale, every image's tail); with under SCALE_MEMBERS, the pooled distance quantile.
MIN_MEMBERS = 100
SCALE_MEMBERS = 5


class MatchError(ValueError):
    """A calibration that is missing, malformed or does not fit its roadmap."""


@dataclass(frozen=True)
class Calibration:
    """How far and how badly redrawn an image may be and still count as known."""

    node_thresholds: tuple[float, ...]  # distance, per node: factor x its images' quantile
    threshold: float  # distance, pooled over every training image (nodes with few images)
    recon_threshold: float  # whole-image reconstruction error
    patch_threshold: float  # worst-patch reconstruction error
    quantile: float
    factor: float
    training_quantile: float  # the training images' pooled distance at `quantile`
    training_max: float
    recon_quantile: float  # the training images' reconstruction error at `quantile`
    recon_max: float
    patch_quantile: float
    patch_max: float
    edges_threshold: float  # the worst patch's drawn edges over the image's
    edges_quantile: float
    edges_max: float
    images: int
    metric: str

    def to_json(self) -> dict[str, Any]:
        return {"format": FORMAT, "version": VERSION, **asdict(self)}


def reconstruction_errors(vae: VAE, images: np.ndarray, latents: np.ndarray) -> np.ndarray:
    """(N, 3) errors of the decoded encoder means (ERRORS: mean squared over the whole image
    and over its worst patch, pixels in [0, 1]; the worst patch's missing edges)."""
    errors = np.empty((len(images), len(ERRORS)), np.float64)
    for start in range(0, len(images), BATCH):
        part = slice(start, start + BATCH)
        drawn = decode_latents(vae, np.asarray(latents[part], np.float32))
        errors[part] = errors_of(torch.from_numpy(drawn), torch.from_numpy(images[part]))
    return errors


@torch.inference_mode()
def look(vae: VAE, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Encoder means (N, D) float32 and reconstruction errors (N, 3) of uint8 images, in one
    pass per batch (each batch is encoded and redrawn while it is in the cache)."""
    latents = np.empty((len(images), vae.config.latent_dim), np.float32)
    errors = np.empty((len(images), len(ERRORS)), np.float64)
    for start in range(0, len(images), BATCH):
        part = slice(start, start + BATCH)
        pixels = torch.from_numpy(np.ascontiguousarray(images[part]))
        mu, _ = vae.encode(to_tensor(pixels).contiguous(memory_format=torch.channels_last))
        latents[part] = mu.numpy()
        errors[part] = errors_of(to_uint8(vae.decode(mu, channels_last=True)), pixels)
    return latents, errors


def look_many(vae: VAE, *image_sets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`look` for a batch job (growth, building) at each set of images in turn, results in that
    order, without copying them into one array: one batch per core at a time, each on one
    torch thread, rather than torch's threads splitting each small convolution (2000 box
    images on two cores: 3.0-3.3 s against 3.5-3.7 s). The thread count is process-wide, so
    one call at a time switches it (a lock)."""
    parts = [x[i : i + BATCH] for x in image_sets for i in range(0, len(x), BATCH)]
    with _THREADS:
        threads = torch.get_num_threads()
        workers = min(threads, len(parts))
        if workers < 2:
            done = [look(vae, part) for part in parts]
        else:
            torch.set_num_threads(1)  # batch jobs only, never a serving process
            try:
                with ThreadPoolExecutor(workers) as pool:
                    done = list(pool.map(lambda part: look(vae, part), parts))
            finally:
                torch.set_num_threads(threads)
    if not done:
        return np.zeros((0, vae.config.latent_dim), np.float32), np.zeros((0, len(ERRORS)))
    return np.concatenate([z for z, _ in done]), np.concatenate([e for _, e in done])


def errors_of(drawn: torch.Tensor, images: torch.Tensor) -> np.ndarray:
    """(B, 3): ERRORS of uint8 (B, H, W, 3) drawings of uint8 images.

    The whole-image error is taken after scaling the drawing by the gain that fits it best to
    the image (`_exposure`): the decoder draws the training looks' average exposure, and a
    scene lit brighter is the same scene. Without it the brightest `shifted` box images were
    refused by this term alone (2.9% of them), while their latents lay where their states' do."""
    drawn, images = drawn.float() / 255.0, images.float() / 255.0
    exposed = drawn * _exposure(drawn, images)
    whole = (exposed - images).pow(2).flatten(1).mean(1)
    gaps = (drawn - images).pow(2)
    patch = max(1, images.shape[1] // PATCHES)
    worst = _patches(gaps.mean(-1)[:, None], patch).max(1).values
    return torch.stack([whole, worst, _missing_edges(exposed, images, patch)], 1).numpy()


def _patches(values: torch.Tensor, patch: int) -> torch.Tensor:
    """(B, P): the mean of (B, 1, H, W) values over each patch, patches moved by half one."""
    return F.avg_pool2d(values, patch, stride=max(1, patch // 2)).flatten(1)


def _missing_edges(drawn: torch.Tensor, images: torch.Tensor, patch: int) -> torch.Tensor:
    """(B,): the largest ratio, over patches, of the drawing's mean edge strength to the
    image's (EDGE_FLOOR added below). A real image has at least the edges its blurry drawing
    has; a cover near the table's colour has none where the drawing has the grid's lines, while
    its squared error stays within a varied task's thresholds (rope-box: 3% of half-covered
    views known without this term, each covered with a grey near the table's)."""
    drawn_edges, image_edges = (_patches(_edge_strength(x), patch) for x in (drawn, images))
    return (drawn_edges / (image_edges + EDGE_FLOOR)).max(1).values


def _edge_strength(pixels: torch.Tensor) -> torch.Tensor:
    """(B, 1, H - 1, W - 1): |dx| + |dy| of the grey of (B, H, W, 3) pixels in [0, 1], blurred
    over 3 x 3 first so that a camera's noise is not taken for edges."""
    grey = F.pad(pixels.mean(-1)[:, None], (1, 1, 1, 1), mode="replicate")
    grey = F.avg_pool2d(grey, 3, stride=1)
    dx = (grey[..., :, 1:] - grey[..., :, :-1]).abs()
    dy = (grey[..., 1:, :] - grey[..., :-1, :]).abs()
    return dx[..., :-1, :] + dy[..., :, :-1]


def _exposure(drawn: torch.Tensor, images: torch.Tensor) -> torch.Tensor:
    """(B, 1, 1, 1): the one gain, within EXPOSURE, that brings a drawing closest to its image.
    One gain, narrowly bounded: a free gain per channel painted a drawing any colour, and a
    solid frame near the table's colour passed as a rope-box scene (19.7% of solid frames
    known; one gain within 0.8-1.25: 2.0%; within 0.87-1.15: 1.0%; without a gain 0.7%)."""
    fit = (drawn * images).sum((1, 2, 3)) / (drawn * drawn).sum((1, 2, 3)).clamp_min(1e-6)
    return fit.clamp(*EXPOSURE)[:, None, None, None]


def distances(roadmap: Roadmap, latents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(matched node, distance to it in the roadmap's metric) for each latent (M, D)."""
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
    """The thresholds from every training image's latent and reconstruction errors (N, 3)."""
    errors = np.asarray(errors, np.float64)
    if len(latents) == 0 or errors.shape != (len(latents), len(ERRORS)):
        raise MatchError(
            f"calibration needs a latent and {len(ERRORS)} errors per training image, got "
            f"{len(latents)} latents and errors of shape {errors.shape}"
        )
    nodes, gaps = distances(roadmap, latents)
    at, recon_at, patch_at, edges_at = (float(np.quantile(x, quantile)) for x in (gaps, *errors.T))
    per_node = [factor * at] * roadmap.num_nodes
    sizes = np.bincount(nodes, minlength=roadmap.num_nodes)
    scale = np.array([np.median(gaps[nodes == k]) if n else 0.0 for k, n in enumerate(sizes)])
    scaled = (sizes[nodes] >= SCALE_MEMBERS) & (scale[nodes] > 0)
    shape = float(np.quantile(gaps[scaled] / scale[nodes[scaled]], quantile)) if scaled.any() else 0
    for node, size in enumerate(sizes):
        if size >= MIN_MEMBERS:
            per_node[node] = factor * float(np.quantile(gaps[nodes == node], quantile))
        elif size >= SCALE_MEMBERS and scale[node] > 0:
            per_node[node] = factor * float(scale[node]) * shape
    return Calibration(
        node_thresholds=tuple(float(t) for t in per_node),
        threshold=factor * at,
        recon_threshold=factor * recon_at,
        patch_threshold=factor * patch_at,
        quantile=quantile,
        factor=factor,
        training_quantile=at,
        training_max=float(gaps.max()),
        recon_quantile=recon_at,
        recon_max=float(errors[:, 0].max()),
        patch_quantile=patch_at,
        patch_max=float(errors[:, 1].max()),
        edges_threshold=factor * edges_at,
        edges_quantile=edges_at,
        edges_max=float(errors[:, 2].max()),
        images=len(gaps),
        metric=roadmap.config.metric,
    )


def ratios(
    roadmap: Roadmap, calibration: Calibration, latents: np.ndarray, errors: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(nearest node (M,), each term over its threshold (M, 4): distance, then ERRORS)."""
    nodes, gaps = distances(roadmap, latents)
    errors = np.asarray(errors, np.float64).reshape(len(nodes), len(ERRORS))
    limits = np.array(
        [calibration.recon_threshold, calibration.patch_threshold, calibration.edges_threshold]
    )
    near = gaps / np.asarray(calibration.node_thresholds)[nodes]
    return nodes, np.column_stack([near, errors / limits])


def match(
    roadmap: Roadmap, calibration: Calibration, latents: np.ndarray, errors: np.ndarray
) -> list[Match]:
    return _matches(*ratios(roadmap, calibration, latents, errors))


def _matches(nodes: np.ndarray, terms: np.ndarray) -> list[Match]:
    return [
        Match(known=bool(s <= 1.0), score=float(s), node=int(n))
        for n, s in zip(nodes, terms.max(1), strict=True)
    ]


def check_ends(
    roadmap: Roadmap,
    calibration: Calibration,
    z_start: np.ndarray,
    z_goal: np.ndarray,
    errors: np.ndarray,
) -> dict[str, Match]:
    """Both ends' matches; UnknownImageError naming the first end that is not known and the
    term that refused it."""
    nodes, terms = ratios(roadmap, calibration, np.stack([z_start, z_goal]), errors)
    start, goal = _matches(nodes, terms)
    matched = {"start": start, "goal": goal}
    end = refused_end(matched)
    if end is not None:
        worst = int(terms[0 if end == "start" else 1].argmax())
        raise UnknownImageError(end, refusal(end, matched[end], calibration, worst), matched)
    return matched


def keep_place(
    roadmap: Roadmap,
    calibration: Calibration,
    z_start: np.ndarray,
    start: int,
    expect: int | None,
    places: Places | None = None,
) -> int:
    """The node to plan from: `expect` (the node a closed loop's last step was meant to reach)
    where the start image is known there too, else the matched `start`. A state whose images
    lie over several nodes (a grown roadmap's twins) would otherwise send each re-plan from
    another twin, round in circles. An `expect` the roadmap does not have is ignored.

    With `places`, not where Algorithm 1 would put the image in `start` and not in `expect`:
    the step went elsewhere (a T-shirt's half unfolded over a sleeve the camera could not
    see; knowing let such an image through at its look-alike in 102 of 1000 test images)."""
    if expect is None or expect == start or not 0 <= expect < roadmap.num_nodes:
        return start
    gap = pair_distances(z_start, roadmap.nodes[expect], roadmap.config.metric)
    if not bool(gap <= calibration.node_thresholds[expect]):
        return start
    if places is not None and places.holds(z_start, start) and not places.holds(z_start, expect):
        return start
    return expect


CANDIDATES = 8  # nodes tried for each end when the two matched are not connected


def connect(
    roadmap: Roadmap,
    calibration: Calibration,
    z_start: np.ndarray,
    z_goal: np.ndarray,
    start: int,
    goal: int,
) -> tuple[int, int]:
    """The nodes to plan between: `start` and `goal` where a path joins them, else, as a
    probabilistic roadmap's query connects its ends, the closest pair (fewest ranks down the
    two lists) of nodes among each end's CANDIDATES nearest that it is known at and that one
    component holds; `start` and `goal` where there is none.

    Why: a grown roadmap keeps small islands of built nodes, images that no later one joined
    (at 500 box tuples after 2000 exploring actions, five of two nodes, every state in them
    also in the main component); an image that lands in one was a task that could not be
    planned."""
    part = roadmap.component
    if part[start] == part[goal]:
        return start, goal
    lists = [
        _known_nodes(roadmap, calibration, z, n) for z, n in ((z_start, start), (z_goal, goal))
    ]
    pairs = [  # fewest ranks, then the start's own: a closed loop's kept place stays
        (i + j, i, s, g)
        for i, s in enumerate(lists[0])
        for j, g in enumerate(lists[1])
        if part[s] == part[g]
    ]
    if not pairs:
        return start, goal
    *_, s, g = min(pairs)
    return int(s), int(g)


def _known_nodes(
    roadmap: Roadmap, calibration: Calibration, z: np.ndarray, first: int
) -> list[int]:
    """`first`, then the nodes among the CANDIDATES nearest `z` that know it, nearest first."""
    near = roadmap.nearest_nodes(z, min(CANDIDATES, roadmap.num_nodes))
    gaps = pair_distances(roadmap.nodes[near].astype(np.float64), z, roadmap.config.metric)
    known = near[gaps <= np.asarray(calibration.node_thresholds)[near]]
    return [first, *(int(n) for n in known if n != first)]


def place_ends(
    roadmap: Roadmap,
    calibration: Calibration,
    z_start: np.ndarray,
    z_goal: np.ndarray,
    errors: np.ndarray,
    expect: int | None = None,
    places: Places | None = None,
) -> tuple[dict[str, Match], int, int]:
    """Both ends' matches and the nodes to plan between (check_ends, keep_place, connect);
    UnknownImageError as check_ends."""
    matched = check_ends(roadmap, calibration, z_start, z_goal, errors)
    start = keep_place(roadmap, calibration, z_start, matched["start"].node, expect, places)
    start, goal = connect(roadmap, calibration, z_start, z_goal, start, matched["goal"].node)
    return matched, start, goal


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
        if document.get("format") != FORMAT or document.get("version") != VERSION:
            raise MatchError(
                f"{path}: expected format {FORMAT!r} version {VERSION}; calibrate the model "
                "again with `lsr calibrate`"
            )
        fields = {k: document[k] for k in Calibration.__dataclass_fields__}
        fields["node_thresholds"] = tuple(float(t) for t in fields["node_thresholds"])
        calibration = Calibration(**fields)
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise MatchError(f"{path}: not a calibration ({exc})") from exc
    if calibration.metric != roadmap.config.metric:
        raise MatchError(
            f"{path}: calibrated in {calibration.metric}, the roadmap measures in "
            f"{roadmap.config.metric}"
        )
    for name in ("threshold", "recon_threshold", "patch_threshold", "edges_threshold"):
        value = getattr(calibration, name)
        if not (isinstance(value, int | float) and np.isfinite(value) and value > 0):
            raise MatchError(f"{path}: {name} must be a positive number")
    per_node = np.asarray(calibration.node_thresholds)
    if len(per_node) != roadmap.num_nodes or not (np.isfinite(per_node) & (per_node > 0)).all():
        raise MatchError(
            f"{path}: node_thresholds must be {roadmap.num_nodes} positive numbers, one per "
            f"roadmap node, got {len(per_node)}"
        )
    return calibration


# Why an image is not known, in the order of ratios()'s terms.
WHY = (
    "its latent lies far from every roadmap region",
    "the model cannot redraw it",
    "the model cannot redraw a part of it",
    "a part of it lacks the edges the model draws there (covered?)",
)


def refusal(end: str, found: Match, calibration: Calibration, term: int) -> str:
    """The reason a plan is refused, naming the end (`start` or `goal`) and the term (an
    index into WHY) that refused it, in plain words."""
    return (
        f"the {end} image is unlike anything this model knows: {WHY[term]} (score "
        f"{found.score:.2f}; known up to 1, which is {calibration.factor:g} times what "
        f"{100 * calibration.quantile:g}% of training images stay within)"
    )
