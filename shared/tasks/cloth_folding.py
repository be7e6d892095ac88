"""Cloth folding (paper section VI-B): a square cloth whose corners fold towards its centre.

A state is the set of folded corners (16 states). An action is the paper's u = (p, r, h): a pick
pixel, a release pixel in a 256 x 256 frame of the top-down camera image, and a grasp height
(0 = at table height, 1 = the top layer only). A fold picks a corner at table height and lays
it on the centre; an unfold picks the top layer of a folded flap and lays it back. Clicks are
matched to these moves within a pixel tolerance, as a human demonstrator's clicks would be.

Image coordinates: row 0 at the top, column 0 on the left; the flat cloth is centred in the
frame with its edges parallel to the image axes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from shared.tasks.folding import ClothAction, FoldingTask, Folds, Move, Pixel

__all__ = ["CORNER_DIRECTIONS", "ClothAction", "ClothFolding", "ClothFoldingConfig", "Folds",
           "Move", "Pixel"]  # fmt: skip

# Direction of each corner from the centre in image axes (column right, row down).
CORNER_DIRECTIONS: dict[str, tuple[int, int]] = {
    "top_left": (-1, -1),
    "top_right": (1, -1),
    "bottom_left": (-1, 1),
    "bottom_right": (1, 1),
}


@dataclass(frozen=True)
class ClothFoldingConfig:
    corners: tuple[str, ...] = tuple(CORNER_DIRECTIONS)
    frame: int = 256  # pixels of the action frame (square), whatever size the model works at
    cloth_pixels: float = 160.0  # side of the flat cloth in that frame
    tolerance: float = 10.0  # pixels a click may land from a move's canonical point
    # Fold: pick a hair outside the corner (a gripper closes on it from there), so that a click
    # a few pixels off still grasps the corner and not the cloth next to it.
    fold_pick: float = 1.04
    # Unfold: pick the flap near its tip (which lies on the centre, with every other tip), at
    # this share of the way from the centre to the corner (on the 9 x 9 cloth: the centre of
    # the flap's corner square, 14 px from every other vertex), and lay it on its mirror image.
    unfold_pick: float = 0.125

    def __post_init__(self) -> None:
        unknown = [c for c in self.corners if c not in CORNER_DIRECTIONS]
        if unknown or len(set(self.corners)) != len(self.corners) or not self.corners:
            raise ValueError(f"corners must be distinct names of {list(CORNER_DIRECTIONS)}")
        if not 0 < self.cloth_pixels < self.frame:
            raise ValueError("the cloth must fit inside the frame")


@dataclass(frozen=True)
class ClothFolding(FoldingTask):
    config: ClothFoldingConfig = field(default_factory=ClothFoldingConfig)
    name: str = "cloth_folding"
    world_entry = "services.sim.cloth_folding.world:ClothFoldingWorld"
    fold_word = "corner"

    @property
    def folds(self) -> tuple[str, ...]:
        return self.config.corners

    # ----- geometry of the moves, in continuous image coordinates (x = column, y = row) -----
    def point(self, corner: str, share: float) -> tuple[float, float]:
        """The point at `share` of the way from the cloth centre to `corner`."""
        c = self.config
        dx, dy = CORNER_DIRECTIONS[corner]
        half = c.cloth_pixels / 2
        return c.frame / 2 + share * half * dx, c.frame / 2 + share * half * dy

    def _pixel(self, xy: tuple[float, float]) -> Pixel:
        return Pixel(row=int(np.floor(xy[1])), col=int(np.floor(xy[0])))

    @cached_property
    def moves(self) -> dict[tuple[str, str], Move]:
        """(kind, corner) -> the move; unfold is the page turn that undoes the fold."""
        c = self.config
        out = {}
        for corner in c.corners:
            fold = ClothAction(
                self._pixel(self.point(corner, c.fold_pick)),
                self._pixel(self.point(corner, 0.0)),
                0,
            )
            unfold = ClothAction(
                self._pixel(self.point(corner, c.unfold_pick)),
                self._pixel(self.point(corner, 1 - c.unfold_pick)),
                1,
            )
            out["fold", corner] = Move("fold", corner, fold)
            out["unfold", corner] = Move("unfold", corner, unfold)
        return out

    def _move_json(self, move: Move) -> dict[str, Any]:
        return {**super()._move_json(move), "corner": move.fold}  # "corner": the first name
