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

import itertools
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, NamedTuple

import numpy as np

from shared.tasks.base import (
    IllegalActionError,
    InvalidActionError,
    InvalidStateError,
    Task,
    parse_row_col,
    state_field,
)
from shared.tasks.spec import ArraySpec, TaskSpec

Folds = tuple[str, ...]  # folded corners, in the order of `ClothFoldingConfig.corners`

# Direction of each corner from the centre in image axes (column right, row down).
CORNER_DIRECTIONS: dict[str, tuple[int, int]] = {
    "top_left": (-1, -1),
    "top_right": (1, -1),
    "bottom_left": (-1, 1),
    "bottom_right": (1, 1),
}


class Pixel(NamedTuple):
    row: int
    col: int


class ClothAction(NamedTuple):
    pick: Pixel
    release: Pixel
    height: int  # 0: grasp every layer at table height; 1: the top layer only


class Move(NamedTuple):
    """A fold or an unfold of one corner, with its canonical action."""

    kind: str  # "fold" | "unfold"
    corner: str
    action: ClothAction


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
class ClothFolding(Task[Folds, ClothAction]):
    config: ClothFoldingConfig = field(default_factory=ClothFoldingConfig)
    name: str = "cloth_folding"

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

    def match(self, action: ClothAction) -> Move | None:
        """The move whose canonical pick and release both lie within tolerance, if any."""
        for move in self.moves.values():
            m = move.action
            if (
                action.height == m.height
                and _distance(action.pick, m.pick) <= self.config.tolerance
                and _distance(action.release, m.release) <= self.config.tolerance
            ):
                return move
        return None

    # ----- description -----
    @cached_property
    def spec(self) -> TaskSpec:  # type: ignore[override]
        c = self.config
        names = ("pick.row", "pick.col", "release.row", "release.col", "height")
        return TaskSpec(
            task=self.name,
            action=ArraySpec(
                dtype="int16",
                shape=(5,),
                names=names,
                counts=(c.frame, c.frame, c.frame, c.frame, 2),
                nullable=True,
                pixels={n: n.split(".")[1] for n in names[:4]},
                frame=c.frame,
            ),
            # one bit per corner: 1 = folded
            state=ArraySpec(
                dtype="int8",
                shape=(len(c.corners),),
                names=tuple(f"folded.{corner}" for corner in c.corners),
                counts=(2,) * len(c.corners),
            ),
        )

    def info(self) -> dict[str, Any]:
        c = self.config
        return {
            "task": self.name,
            "folds": list(c.corners),
            "num_states": len(self.all_states()),
            "num_transitions": sum(len(self.legal_actions(s)) for s in self.all_states()),
            "image_frame": c.frame,
            "tolerance_px": c.tolerance,
            "action_fields": list(self.spec.action.names),
            "state_format": {"folds": "the folded corners, as a set"},
            "action_format": {
                "pick": {"row": f"0..{c.frame - 1}", "col": f"0..{c.frame - 1}"},
                "release": {"row": f"0..{c.frame - 1}", "col": f"0..{c.frame - 1}"},
                "height": "0 = grasp at table height, 1 = the top layer only",
            },
            "moves": [
                {"kind": m.kind, "corner": m.corner, "action": self.action_to_json(m.action)}
                for m in self.moves.values()
            ],
            "spec": self.spec.to_json(),
        }

    # ----- JSON codecs -----
    def parse_state(self, obj: Any) -> Folds:
        corners = self.config.corners
        folds = state_field(obj, "folds", "list")
        if not isinstance(folds, list | tuple):
            raise InvalidStateError("state.folds: expected a list of fold names")
        seen: set[str] = set()
        for i, fold in enumerate(folds):
            if not isinstance(fold, str) or fold not in corners:
                raise InvalidStateError(
                    f"state.folds[{i}]: unknown fold {fold!r}; known folds are {list(corners)}"
                )
            if fold in seen:
                raise InvalidStateError(f"state.folds[{i}]: fold {fold!r} appears twice")
            seen.add(fold)
        return tuple(c for c in corners if c in seen)

    def state_to_json(self, state: Folds) -> dict[str, Any]:
        return {"folds": list(state)}

    def parse_action(self, obj: Any) -> ClothAction:
        if not isinstance(obj, dict):
            raise InvalidActionError(
                "action: expected an object with 'pick', 'release' and 'height'"
            )
        extra = sorted(set(obj) - {"pick", "release", "height"})
        if extra:
            raise InvalidActionError(f"action: unknown key {extra[0]!r}")
        frame = self.config.frame
        pick, release = (
            Pixel(*parse_row_col(obj.get(key), f"action.{key}", frame, frame))
            for key in ("pick", "release")
        )
        height = obj.get("height")
        if isinstance(height, bool) or height not in (0, 1):
            raise InvalidActionError(
                f"action.height: expected 0 (table) or 1 (top layer), got {height!r}"
            )
        return ClothAction(pick, release, int(height))

    def action_to_json(self, action: ClothAction) -> dict[str, Any]:
        return {
            "pick": {"row": int(action.pick.row), "col": int(action.pick.col)},
            "release": {"row": int(action.release.row), "col": int(action.release.col)},
            "height": int(action.height),
        }

    # ----- rules -----
    def check_action(self, state: Folds, action: ClothAction) -> None:
        move = self.match(action)
        if move is None:
            raise IllegalActionError(
                f"no fold or unfold matches pick {tuple(action.pick)}, release "
                f"{tuple(action.release)}, height {action.height} (within "
                f"{self.config.tolerance:g} px); moves: {self._move_summary()}"
            )
        if move.kind == "fold" and move.corner in state:
            raise IllegalActionError(f"corner {move.corner!r} is already folded")
        if move.kind == "unfold" and move.corner not in state:
            raise IllegalActionError(f"corner {move.corner!r} is not folded: nothing to unfold")

    def _move_summary(self) -> str:
        return "; ".join(
            f"{m.kind} {m.corner}: pick {tuple(m.action.pick)} -> {tuple(m.action.release)} "
            f"h={m.action.height}"
            for m in self.moves.values()
        )

    def legal_actions(self, state: Folds) -> list[ClothAction]:
        return [
            m.action
            for m in self.moves.values()
            if (m.kind == "fold") != (m.corner in state)  # fold the flat, unfold the folded
        ]

    def _apply_legal(self, state: Folds, action: ClothAction) -> Folds:
        move = self.match(action)
        assert move is not None
        folded = set(state) ^ {move.corner}
        return tuple(c for c in self.config.corners if c in folded)

    def all_states(self) -> tuple[Folds, ...]:
        return self._all_states

    @cached_property
    def _all_states(self) -> tuple[Folds, ...]:
        corners = self.config.corners
        return tuple(
            subset for k in range(len(corners) + 1) for subset in itertools.combinations(corners, k)
        )

    # ----- array codecs -----
    def state_to_array(self, state: Folds) -> np.ndarray:
        return np.array([c in state for c in self.config.corners], dtype=np.int8)

    def array_to_state(self, array: np.ndarray) -> Folds:
        bits = np.asarray(array)
        if bits.shape != self.spec.state.shape or not np.isin(bits, (0, 1)).all():  # type: ignore[union-attr]
            raise InvalidStateError(f"state array: expected {len(self.config.corners)} bits")
        return tuple(c for c, b in zip(self.config.corners, bits.tolist(), strict=True) if b)

    def action_to_array(self, action: ClothAction | None) -> np.ndarray:
        if action is None:
            return np.full(5, -1, dtype=np.int16)
        return np.array([*action.pick, *action.release, action.height], dtype=np.int16)

    def array_to_action(self, array: np.ndarray) -> ClothAction | None:
        v = [int(x) for x in np.asarray(array).reshape(-1)]
        if all(x < 0 for x in v):
            return None
        return ClothAction(Pixel(v[0], v[1]), Pixel(v[2], v[3]), v[4])


def _distance(a: Pixel, b: Pixel) -> float:
    return float(np.hypot(a.row - b.row, a.col - b.col))
