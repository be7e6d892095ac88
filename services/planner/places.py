"""Which node an image belongs to by Algorithm 1's own test: within epsilon of one of the
node's points (the roadmap's training latents), the distance at which building joined them.

A closed loop plans on from the node its last step was meant to reach while the image is
known there (`knowing.keep_place`); knowing is generous (twice a high quantile), so an image
of a look-alike view was known at its neighbour too. Where Algorithm 1 would put the image in
another node and not in the expected one, the loop has gone elsewhere and plans from there.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from safetensors import SafetensorError, safe_open
from scipy.spatial import cKDTree

from services.planner.regions import metric_p
from services.planner.roadmap import Roadmap

MEMBERS = "members.safetensors"  # services.planner.members writes it beside the roadmap


@dataclass
class Places:
    """The roadmap's points with their nodes; trees built on first use, one per node."""

    points: np.ndarray  # (2N, D) float64, the roadmap's point order
    point_node: np.ndarray  # (2N,) node of each point, -1 where pruned
    epsilon: float
    metric: str
    _trees: dict[int, cKDTree | None] = field(default_factory=dict, init=False, repr=False)

    @classmethod
    def load(cls, folder: Path | str, roadmap: Roadmap) -> Places | None:
        """The roadmap's places, or None where its folder keeps no readable points that fit
        it (an older model: the loop then keeps its place wherever the image is known)."""
        path = Path(folder) / MEMBERS
        try:
            with safe_open(str(path), framework="numpy") as f:
                points = f.get_tensor("points")
        except (OSError, SafetensorError, KeyError):
            return None
        if points.ndim != 2 or points.shape != (len(roadmap.point_node), roadmap.nodes.shape[1]):
            return None
        return cls(points.astype(np.float64), roadmap.point_node, roadmap.epsilon,
                   roadmap.config.metric)  # fmt: skip

    def holds(self, z: np.ndarray, node: int) -> bool:
        """Algorithm 1 would put `z` in `node`: one of its points lies closer than epsilon."""
        if node not in self._trees:
            mine = self.points[self.point_node == node]
            self._trees[node] = cKDTree(mine) if len(mine) else None
        tree = self._trees[node]
        if tree is None:
            return False
        gap, _ = tree.query(np.asarray(z, np.float64), p=metric_p(self.metric))
        return bool(gap < self.epsilon)
