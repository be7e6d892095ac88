"""What every folding task shares: states are sets of folds, actions are the paper's u = (p, r, h).

An action is a pick pixel, a release pixel in a square frame of the task's camera image, and a
grasp height (0 = at table height, every layer under the point; 1 = the top layer only). Each
move (fold or unfold one fold) has a canonical action; clicks are matched to moves within a
pixel tolerance, as a human demonstrator's clicks would be. Subclasses give the folds, the
moves and, where some moves wait for others, the rule (`refusal`).
"""

from __future__ import annotations

import itertools
from abc import abstractmethod
from collections.abc import Mapping
from functools import cached_property
from typing import Any, ClassVar, NamedTuple

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

Folds = tuple[str, ...]  # the folds a cloth shows, in the order of the task's `folds`


class Pixel(NamedTuple):
    row: int
    col: int


class ClothAction(NamedTuple):
    pick: Pixel
    release: Pixel
    height: int  # 0: grasp every layer at table height; 1: the top layer only


class Move(NamedTuple):
    """A fold or an unfold of one fold, with its canonical action."""

    kind: str  # "fold" | "unfold"
    fold: str
    action: ClothAction


class FoldingTask(Task[Folds, ClothAction]):
    """States, codecs and move matching of a cloth whose states are sets of folds."""

    config: Any  # has `frame` (pixels of the square action frame) and `tolerance` (pixels a
    # click may land from a move's canonical point)
    d_m: ClassVar[Mapping[str, float]] = {"l1": 13.5, "l2": 3.5, "inf": 2.0}  # the paper's folds'

    def state_label(self, state: Folds) -> str:
        return " ".join(map(self.short_name, state)) or "flat"

    @property
    def frame(self) -> int:
        return self.config.frame

    @property
    def tolerance(self) -> float:
        return self.config.tolerance

    @property
    @abstractmethod
    def folds(self) -> tuple[str, ...]:
        """The fold names, in the order states list them."""

    @property
    @abstractmethod
    def moves(self) -> dict[tuple[str, str], Move]:
        """(kind, fold) -> the move."""

    def short_name(self, fold: str) -> str:
        """A few letters for labels under small pictures: the initials of the name's words."""
        return "".join(w[0].upper() for w in fold.split("_"))

    def locks(self) -> dict[str, tuple[str, ...]]:
        """For each fold, the folds that hold it in place while they are folded: its moves wait
        for them. Tasks whose moves wait for others override it; the viewer reads it too."""
        return {fold: () for fold in self.folds}

    def refusal(self, state: Folds, move: Move) -> str | None:
        """Why `move` may not be made in `state` (beyond folding the folded or unfolding the
        flat), or None."""
        held = [fold for fold in self.locks()[move.fold] if fold in state]
        if held:
            return f"{move.fold!r} cannot {move.kind} while {held[0]!r} is folded over it"
        return None

    def match(self, action: ClothAction) -> Move | None:
        """The move whose canonical pick and release both lie within tolerance, if any."""
        for move in self.moves.values():
            m = move.action
            if (
                action.height == m.height
                and _distance(action.pick, m.pick) <= self.tolerance
                and _distance(action.release, m.release) <= self.tolerance
            ):
                return move
        return None

    def same_action(self, first: np.ndarray, second: np.ndarray) -> bool:
        """Two clicks that name one move are one action (a demonstrator's clicks spread over
        the tolerance); actions naming no move are the same only when equal."""
        moves = [self.match(a) if a else None for a in map(self.array_to_action, (first, second))]
        if moves[0] is None or moves[1] is None:
            return bool(np.array_equal(first, second))
        return moves[0] is moves[1]

    # ----- description -----
    @cached_property
    def spec(self) -> TaskSpec:  # type: ignore[override]
        names = ("pick.row", "pick.col", "release.row", "release.col", "height")
        f = self.frame
        return TaskSpec(
            task=self.name,
            action=ArraySpec(
                dtype="int16",
                shape=(5,),
                names=names,
                counts=(f, f, f, f, 2),
                nullable=True,
                pixels={n: n.split(".")[1] for n in names[:4]},
                frame=f,
            ),
            # one bit per fold: 1 = folded
            state=ArraySpec(
                dtype="int8",
                shape=(len(self.folds),),
                names=tuple(f"folded.{fold}" for fold in self.folds),
                counts=(2,) * len(self.folds),
            ),
        )

    def info(self) -> dict[str, Any]:
        f = self.frame
        return {
            "task": self.name,
            "folds": list(self.folds),
            **self.markers_info(),
            "locked_by": {fold: list(held) for fold, held in self.locks().items()},
            "num_states": len(self.all_states()),
            "num_views": self.num_views(),  # what a camera above can tell apart
            "num_transitions": sum(len(self.legal_actions(s)) for s in self.all_states()),
            "image_frame": f,
            "tolerance_px": self.tolerance,
            "action_fields": list(self.spec.action.names),
            "state_format": {"folds": "the folds the cloth shows, as a set"},
            "action_format": {
                "pick": {"row": f"0..{f - 1}", "col": f"0..{f - 1}"},
                "release": {"row": f"0..{f - 1}", "col": f"0..{f - 1}"},
                "height": "0 = grasp at table height, 1 = the top layer only",
            },
            "moves": [self._move_json(m) for m in self.moves.values()],
            "spec": self.spec.to_json(),
        }

    def _move_json(self, move: Move) -> dict[str, Any]:
        return {"kind": move.kind, "fold": move.fold, "action": self.action_to_json(move.action)}

    # ----- JSON codecs -----
    def parse_state(self, obj: Any) -> Folds:
        folds = state_field(obj, "folds", "list")
        if not isinstance(folds, list | tuple):
            raise InvalidStateError("state.folds: expected a list of fold names")
        seen: set[str] = set()
        for i, fold in enumerate(folds):
            if not isinstance(fold, str) or fold not in self.folds:
                raise InvalidStateError(
                    f"state.folds[{i}]: unknown fold {fold!r}; known folds are {list(self.folds)}"
                )
            if fold in seen:
                raise InvalidStateError(f"state.folds[{i}]: fold {fold!r} appears twice")
            seen.add(fold)
        return tuple(c for c in self.folds if c in seen)

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
        f = self.frame
        pick, release = (
            Pixel(*parse_row_col(obj.get(key), f"action.{key}", f, f))
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
                f"{self.tolerance:g} px); moves: {self._move_summary()}"
            )
        what = self.fold_word
        if move.kind == "fold" and move.fold in state:
            raise IllegalActionError(f"{what} {move.fold!r} is already folded")
        if move.kind == "unfold" and move.fold not in state:
            raise IllegalActionError(f"{what} {move.fold!r} is not folded: nothing to unfold")
        reason = self.refusal(state, move)
        if reason is not None:
            raise IllegalActionError(reason)

    fold_word = "fold"  # how error messages name a fold ("corner" for a square cloth)

    def _move_summary(self) -> str:
        return "; ".join(
            f"{m.kind} {m.fold}: pick {tuple(m.action.pick)} -> {tuple(m.action.release)} "
            f"h={m.action.height}"
            for m in self.moves.values()
        )

    def legal_actions(self, state: Folds) -> list[ClothAction]:
        return [
            m.action
            for m in self.moves.values()
            if (m.kind == "fold") != (m.fold in state) and self.refusal(state, m) is None
        ]

    def _apply_legal(self, state: Folds, action: ClothAction) -> Folds:
        move = self.match(action)
        assert move is not None
        folded = set(state) ^ {move.fold}
        return tuple(c for c in self.folds if c in folded)

    def all_states(self) -> tuple[Folds, ...]:
        return self._all_states

    @cached_property
    def _all_states(self) -> tuple[Folds, ...]:
        return tuple(
            subset
            for k in range(len(self.folds) + 1)
            for subset in itertools.combinations(self.folds, k)
        )

    # ----- array codecs -----
    def state_to_array(self, state: Folds) -> np.ndarray:
        return np.array([c in state for c in self.folds], dtype=np.int8)

    def array_to_state(self, array: np.ndarray) -> Folds:
        bits = np.asarray(array)
        if bits.shape != self.spec.state.shape or not np.isin(bits, (0, 1)).all():  # type: ignore[union-attr]
            raise InvalidStateError(f"state array: expected {len(self.folds)} bits")
        return tuple(c for c, b in zip(self.folds, bits.tolist(), strict=True) if b)

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
