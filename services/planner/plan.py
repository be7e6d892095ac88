"""Planning in the roadmap: nearest nodes of start and goal, all shortest paths, images cached.

This is the in-process core that the planner service and `lsr plan` wrap.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from services.encoder.checkpoint import decode_latents, encode_images
from services.encoder.model import VAE
from services.planner import knowing
from services.planner.knowing import Calibration
from services.planner.places import Places
from services.planner.roadmap import Roadmap
from shared.plans import Match


@dataclass(frozen=True)
class LatentPlan:
    nodes: list[int]  # roadmap node ids from start to goal
    latents: np.ndarray  # (len(nodes), D) the nodes' representative latents


class VisualPlanner:
    """Plans between images; each node is decoded at most once, then served from the cache.

    With a calibration it refuses (UnknownImageError) an end unlike anything the model knows;
    without one (unit tests of the search alone) every image counts as known.
    """

    def __init__(
        self,
        vae: VAE,
        roadmap: Roadmap,
        calibration: Calibration | None = None,
        places: Places | None = None,
    ) -> None:
        self.vae = vae
        self.roadmap = roadmap
        self.calibration = calibration
        self.places = places  # where a closed loop went when it did not go as planned
        self._images: dict[int, np.ndarray] = {}

    def encode(self, images: np.ndarray) -> np.ndarray:
        """uint8 (N, H, W, 3) -> encoder means (N, D)."""
        self._check(images)
        return encode_images(self.vae, images)[0]

    def look(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Encoder means and reconstruction errors: what planning and knowing need."""
        self._check(images)
        return knowing.look(self.vae, images)

    def _check(self, images: np.ndarray) -> None:
        size = self.vae.config.image_size
        if images.ndim != 4 or images.shape[1:] != (size, size, 3) or images.dtype != np.uint8:
            raise ValueError(
                f"images must be uint8 of shape (N, {size}, {size}, 3), "
                f"got {images.dtype} {images.shape}"
            )

    def match(
        self, z_start: np.ndarray, z_goal: np.ndarray, errors: np.ndarray
    ) -> dict[str, Match] | None:
        """How well the model knows each end; None without a calibration."""
        if self.calibration is None:
            return None
        both = np.stack([z_start, z_goal])
        start, goal = knowing.match(self.roadmap, self.calibration, both, errors)
        return {"start": start, "goal": goal}

    def plan_latent(
        self,
        z_start: np.ndarray,
        z_goal: np.ndarray,
        max_paths: int,
        errors: np.ndarray | None = None,
        expect: int | None = None,
        avoid: Sequence[tuple[int, int]] = (),
    ) -> list[LatentPlan]:
        """All shortest paths; UnknownImageError when an end is not known (a calibrated
        planner needs both images' reconstruction errors, from `look`).

        `expect`: the node a closed loop's last step was meant to reach (`knowing.keep_place`);
        `avoid`: steps no path takes (Roadmap.shortest_paths).
        """
        if self.calibration is not None:
            if errors is None:
                raise ValueError("a calibrated planner needs the images' reconstruction errors")
            _, start, goal = knowing.place_ends(
                self.roadmap, self.calibration, z_start, z_goal, errors, expect, self.places
            )
        else:
            start, goal = (int(n) for n in self.roadmap.nearest_node(np.stack([z_start, z_goal])))
        paths = self.roadmap.shortest_paths(start, goal, max_paths, avoid)
        return [LatentPlan(p, self.roadmap.nodes[p]) for p in paths]

    def plan(self, start: np.ndarray, goal: np.ndarray, max_paths: int = 16) -> list[LatentPlan]:
        z, errors = self.look(np.stack([start, goal]))
        return self.plan_latent(z[0], z[1], max_paths, errors)

    def node_images(self, nodes: list[int]) -> list[np.ndarray]:
        """Decoded representatives, decoding only the nodes not seen before."""
        missing = sorted({n for n in nodes if n not in self._images})
        if missing:
            decoded = decode_latents(self.vae, self.roadmap.nodes[missing].astype(np.float32))
            self._images.update(zip(missing, decoded, strict=True))
        return [self._images[n] for n in nodes]
