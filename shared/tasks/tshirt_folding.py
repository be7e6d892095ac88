"""T-shirt folding (the paper's deformable study): a short-sleeved T-shirt lying flat.

The neck is at the top of the image, the sleeves to the left and right. A state is the set of
folds the shirt shows, from the two sleeves (laid over the body along the armhole line), the two
sides (the outer sixth of the body, carrying its sleeve, so that the two side flaps and the
sleeves they carry lie side by side, never on each other) and the bottom half (laid up over
the top, carrying everything): 32 states. A sleeve folds or unfolds only while its side and the
bottom half are unfolded; a side only while the bottom half is unfolded; the bottom half in any
state: 80 directed transitions.

Actions are the paper's u = (p, r, h) in the 256 x 256 frame (`shared.tasks.folding`). The
garment's shape is given in metres (x right, y up, origin at the body's centre) and drawn into
the frame at `pixels_per_metre`, so that the world and the moves agree on where a fold line is.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from shared.tasks.folding import ClothAction, FoldingTask, Folds, Move, Pixel

FOLDS = ("left_sleeve", "right_sleeve", "left_side", "right_side", "bottom_half")
SHORT = {"left_sleeve": "a", "right_sleeve": "b", "left_side": "L", "right_side": "R"}
SHORT["bottom_half"] = "H"  # the letters of the reference probe's picture
SIDE_OF = {"left_sleeve": "left_side", "right_sleeve": "right_side"}


@dataclass(frozen=True)
class TshirtConfig:
    body_width: float = 0.36  # metres
    body_height: float = 0.40
    sleeve_length: float = 0.045  # out from the armhole; folded, it lies inside its side strip
    sleeve_width: float = 0.10  # along the armhole, from the shoulder down
    # The side strip: a sixth of the body. Folded, each side lays its sleeve (unfolded) into
    # the middle, between the two flaps; with wider strips or longer sleeves that sleeve lies on
    # the other side's flap or sleeve, and turning the lower one back from under it drags the
    # upper one along (measured: 2 of 4 such unfolds failed). `__post_init__` keeps them apart.
    side_width: float = 0.06
    neck_width: float = 0.06
    neck_depth: float = 0.05
    frame: int = 256
    pixels_per_metre: float = 430.0  # the flat shirt spans 194 x 172 px of the frame
    tolerance: float = 10.0  # pixels a click may land from a move's canonical point
    pick_outside: float = 0.005  # m: a fold picks this far outside the flap's edge
    unfold_inset: float = 0.02  # m: an unfold picks the flap this far inside its folded edge
    side_pick_y: float = -0.09  # m: sides are picked low on the strip, away from the sleeves
    half_pick_x: float = 0.07  # m: the bottom half is picked beside the neck notch, where a
    # folded hem lies on the body (over the notch it would be a single layer)

    def __post_init__(self) -> None:
        if not 0 < self.sleeve_length < self.side_width:
            raise ValueError("a folded sleeve must lie inside its side strip")
        if not 0 < 2 * self.side_width <= self.body_width / 2 + 1e-9:
            raise ValueError("the side strips must not reach past the middle")
        # a folded side lays its sleeve's root at x = +-(armhole - 2 side_width), pointing in
        if self.sleeve_length >= self.body_width / 2 - 2 * self.side_width - 0.005:
            raise ValueError("a sleeve carried by its side must not reach the other side's")
        half_w = self.body_width / 2 + self.sleeve_length
        if 2 * half_w * self.pixels_per_metre >= self.frame:
            raise ValueError("the shirt must fit inside the frame")

    @property
    def armhole(self) -> float:
        """x of the right armhole line (the left one is its mirror)."""
        return self.body_width / 2

    @property
    def side_line(self) -> float:
        """x of the right side's fold line."""
        return self.body_width / 2 - self.side_width


@dataclass(frozen=True)
class TshirtFolding(FoldingTask):
    config: TshirtConfig = field(default_factory=TshirtConfig)
    name: str = "tshirt_folding"
    world_entry = "services.sim.tshirt_folding.world:TshirtFoldingWorld"
    # where the method has to earn its results, its images look like a camera's (the paper's
    # real-camera study)
    default_look = "camera"

    @property
    def folds(self) -> tuple[str, ...]:
        return FOLDS

    def to_frame(self, x: float, y: float) -> tuple[float, float]:
        """Metres on the flat shirt -> continuous (col, row) of the action frame."""
        c = self.config
        return c.frame / 2 + x * c.pixels_per_metre, c.frame / 2 - y * c.pixels_per_metre

    def _pixel(self, x: float, y: float) -> Pixel:
        col, row = self.to_frame(x, y)
        return Pixel(row=int(np.floor(row)), col=int(np.floor(col)))

    def fold_line(self, fold: str) -> tuple[np.ndarray, np.ndarray]:
        """(a point on the line, the unit normal pointing into the flap), in metres."""
        c = self.config
        if fold == "bottom_half":
            return np.array([0.0, 0.0]), np.array([0.0, -1.0])
        sign = -1.0 if fold.startswith("left") else 1.0
        x = c.armhole if fold in SIDE_OF else c.side_line
        return np.array([sign * x, 0.0]), np.array([sign, 0.0])

    @cached_property
    def moves(self) -> dict[tuple[str, str], Move]:
        """A fold picks just outside the flap's edge (every layer) and lays it on its mirror
        image over the fold line; the unfold picks the flap's top layer just inside its folded
        edge and lays it back."""
        c = self.config
        top = c.body_height / 2
        sleeve_y = top - c.sleeve_width / 2
        edges = {  # (the flap's outer edge, distance from the fold line) and where along it
            "left_sleeve": (c.sleeve_length, sleeve_y),
            "right_sleeve": (c.sleeve_length, sleeve_y),
            "left_side": (c.side_width, c.side_pick_y),
            "right_side": (c.side_width, c.side_pick_y),
            "bottom_half": (top, c.half_pick_x),
        }
        out = {}
        for fold in FOLDS:
            point, normal = self.fold_line(fold)
            depth, along = edges[fold]
            tangent = np.array([normal[1], -normal[0]])
            base = point + along * np.abs(tangent)  # along the line, towards +x or +y

            def at(distance: float, base: np.ndarray = base, normal: np.ndarray = normal) -> Pixel:
                return self._pixel(*(base + distance * normal))

            out["fold", fold] = Move(
                "fold",
                fold,
                ClothAction(at(depth + c.pick_outside), at(-depth - c.pick_outside), 0),
            )
            inset = depth - c.unfold_inset
            out["unfold", fold] = Move("unfold", fold, ClothAction(at(-inset), at(inset), 1))
        return out

    def short_name(self, fold: str) -> str:
        return SHORT[fold]

    def locks(self) -> dict[str, tuple[str, ...]]:
        sleeves = {sleeve: ("bottom_half", side) for sleeve, side in SIDE_OF.items()}
        sides = {side: ("bottom_half",) for side in SIDE_OF.values()}
        return {"bottom_half": ()} | sides | sleeves

    def hidden(self, state: Folds) -> frozenset[str]:
        """With the bottom half folded, a folded side's sleeve lies under it, inside the flap or
        on it: a camera from above sees neither (docs/tasks/tshirt-folding.md)."""
        if "bottom_half" not in state:
            return frozenset()
        return frozenset(sleeve for sleeve, side in SIDE_OF.items() if side in state)

    def view(self, state: Folds) -> tuple[Folds, tuple[str, ...]]:
        """The folds a camera above sees, and the sleeves it cannot see (folded or not): the
        32 states give 25 views."""
        hidden = self.hidden(state)
        return tuple(f for f in state if f not in hidden), tuple(sorted(hidden))

    def view_to_json(self, state: Folds) -> dict[str, Any]:
        """`{"folds": [...], "hidden": [...]}`: the folds seen, and the sleeves no image shows."""
        folds, hidden = self.view(state)
        return {"folds": list(folds), "hidden": list(hidden)}

    def info(self) -> dict[str, Any]:
        c = self.config
        return {
            **super().info(),
            "garment": {
                "body_width_m": c.body_width,
                "body_height_m": c.body_height,
                "sleeve_length_m": c.sleeve_length,
                "side_width_m": c.side_width,
                "pixels_per_metre": c.pixels_per_metre,
            },
            "rules": [
                "a sleeve folds or unfolds only while its side and bottom_half are unfolded",
                "a side folds or unfolds only while bottom_half is unfolded",
                "bottom_half folds or unfolds in any state",
            ],
        }
