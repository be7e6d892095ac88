"""What a task's arrays look like, declared once and stored with every dataset.

An `ArraySpec` describes one array field before any array exists (as dm_env's
`BoundedArray` and Gymnasium's `MultiDiscrete(nvec, start=...)` do): its dtype, shape, element
names and the integer range of each element. A `TaskSpec` bundles the action and state specs of
one task. Datasets write it into their manifest, so consumers (APN widths, state readers, node
labels) take shapes from the data they read, not from a registry lookup.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

NULL = -1  # an action array of all NULL encodes "no action"


class SpecError(ValueError):
    """An array or a JSON spec that does not match what it should; the message names it."""


@dataclass(frozen=True)
class ArraySpec:
    """Integer array whose element i lies in start .. start + counts[i] - 1 (flattened order)."""

    dtype: str
    shape: tuple[int, ...]
    names: tuple[str, ...]
    counts: tuple[int, ...]
    start: int = 0
    nullable: bool = False  # the all-NULL array is allowed too (no-action pairs)
    # Elements that are pixel coordinates: name -> image axis ("row" or "col"), in a square
    # frame of `frame` pixels (LeRobot keeps such facts in a feature's `info`).
    pixels: dict[str, str] = field(default_factory=dict)
    frame: int | None = None
    # How an element's JSON value maps to its stored integer, for declared (imported) tasks:
    # {"low": L} an integer L..L+count-1 stored as value - L; {"categories": [...]} a name stored
    # as its index; {"float": [lo, hi]} a number stored as the nearest of `count` evenly spaced
    # levels from lo to hi. Absent: the integer is stored as it is.
    encodings: dict[str, dict[str, Any]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "shape", tuple(int(s) for s in self.shape))
        object.__setattr__(self, "names", tuple(self.names))
        object.__setattr__(self, "counts", tuple(int(c) for c in self.counts))
        size = int(np.prod(self.shape))
        if len(self.names) != size or len(self.counts) != size:
            raise SpecError(
                f"spec: {len(self.names)} names and {len(self.counts)} counts for {size} elements"
            )
        if min(self.counts) < 1:
            raise SpecError("spec: every count must be at least 1")
        try:
            info = np.iinfo(np.dtype(self.dtype))
        except (TypeError, ValueError):
            raise SpecError(f"spec: dtype {self.dtype!r} is not an integer dtype") from None
        low = min(self.start, NULL) if self.nullable else self.start
        high = self.start + max(self.counts) - 1
        if low < info.min or high > info.max:
            raise SpecError(
                f"spec: dtype {self.dtype} holds {info.min}..{info.max}, "
                f"the values need {low}..{high}"
            )
        unknown = sorted(set(self.pixels) - set(self.names))
        if unknown or any(axis not in ("row", "col") for axis in self.pixels.values()):
            raise SpecError(f"spec: pixels must map element names to 'row' or 'col' ({unknown})")
        if self.pixels and self.frame is None:
            raise SpecError("spec: pixel elements need a frame size")
        for name, encoding in self.encodings.items():
            self._check_encoding(name, encoding)

    def _check_encoding(self, name: str, encoding: Any) -> None:
        if name not in self.names:
            raise SpecError(f"spec: encoding for unknown element {name!r}")
        count = self.counts[self.names.index(name)]
        if not isinstance(encoding, dict) or len(encoding) != 1:
            raise SpecError(f"spec: encoding of {name}: expected one of low, categories, float")
        ((kind, value),) = encoding.items()
        if kind == "low":
            if isinstance(value, bool) or not isinstance(value, int):
                raise SpecError(f"spec: encoding of {name}: low must be an integer")
        elif kind == "categories":
            if (
                not isinstance(value, list)
                or len(value) != count
                or not all(isinstance(c, str) and c for c in value)
                or len(set(value)) != len(value)
            ):
                raise SpecError(
                    f"spec: encoding of {name}: {count} distinct non-empty category names needed"
                )
        elif kind == "float":
            if (
                not isinstance(value, list)
                or len(value) != 2
                or not all(isinstance(v, int | float) and np.isfinite(v) for v in value)
                or not value[0] < value[1]
                or count < 2
            ):
                raise SpecError(f"spec: encoding of {name}: float needs [low, high], low < high")
        else:
            raise SpecError(f"spec: encoding of {name}: unknown kind {kind!r}")

    def validate(self, array: np.ndarray, field_name: str, batched: bool = True) -> None:
        """Raise SpecError naming the field unless `array` (a batch when batched) fits."""
        array = np.asarray(array)
        shape = array.shape[1:] if batched else array.shape
        if array.dtype != np.dtype(self.dtype) or shape != self.shape:
            raise SpecError(
                f"{field_name}: expected {self.dtype} of shape {self.shape}, "
                f"got {array.dtype} {shape}"
            )
        flat = array.reshape(-1, len(self.names)).astype(np.int64)
        low = np.array([self.start] * len(self.counts))
        bad = (flat < low) | (flat >= low + np.array(self.counts))
        if self.nullable:
            bad &= ~(flat == NULL).all(axis=1, keepdims=True)
        if bad.any():
            row, col = (int(i) for i in np.argwhere(bad)[0])
            raise SpecError(
                f"{field_name}[{row}]: {self.names[col]} = {int(flat[row, col])} is out of range "
                f"{self.start}..{self.start + self.counts[col] - 1}"
            )

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "dtype": self.dtype,
            "shape": list(self.shape),
            "names": list(self.names),
            "counts": list(self.counts),
            "start": self.start,
            "nullable": self.nullable,
        }
        if self.pixels:
            out["pixels"] = dict(self.pixels)
            out["frame"] = self.frame
        if self.encodings:
            out["encodings"] = {k: dict(v) for k, v in self.encodings.items()}
        return out

    @classmethod
    def from_json(cls, obj: Any, where: str) -> ArraySpec:
        if not isinstance(obj, dict):
            raise SpecError(f"{where}: expected an object")
        try:
            return cls(
                dtype=str(obj["dtype"]),
                shape=tuple(obj["shape"]),
                names=tuple(obj["names"]),
                counts=tuple(obj["counts"]),
                start=int(obj.get("start", 0)),
                nullable=bool(obj.get("nullable", False)),
                pixels=dict(obj.get("pixels", {})),
                frame=obj.get("frame"),
                encodings=dict(obj.get("encodings", {})),
            )
        except KeyError as exc:
            raise SpecError(f"{where}: missing {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            raise SpecError(f"{where}: {exc}") from None


@dataclass(frozen=True)
class TaskSpec:
    """The arrays of one task: `u` (actions) and, where states are known, `state1`/`state2`."""

    task: str
    action: ArraySpec
    state: ArraySpec | None
    # Action elements whose swap undoes a move (box stacking: pick <-> release puts the box
    # back), so every demonstrated pair teaches the APN its reverse too. Empty: no such symmetry.
    # Knowledge about the moves, not the arrays: specs compare equal without it, so data and
    # experience recorded before a task declared it still match.
    undo: tuple[tuple[str, str], ...] = field(default=(), compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "undo", tuple(tuple(pair) for pair in self.undo))
        named = [name for pair in self.undo for name in pair]
        if any(len(pair) != 2 for pair in self.undo) or len(set(named)) != len(named):
            raise SpecError("spec.undo: pairs of distinct action elements, each named once")
        unknown = sorted(set(named) - set(self.action.names))
        if unknown:
            raise SpecError(f"spec.undo: {unknown} are not action elements")

    def undone(self, u: np.ndarray) -> np.ndarray:
        """The actions (N, *shape) that undo `u`: its `undo` elements swapped."""
        flat = u.reshape(len(u), -1).copy()
        for a, b in self.undo:
            i, j = self.action.names.index(a), self.action.names.index(b)
            flat[:, [i, j]] = flat[:, [j, i]]
        return flat.reshape(u.shape)

    def to_json(self) -> dict[str, Any]:
        out = {
            "task": self.task,
            "action": self.action.to_json(),
            "state": None if self.state is None else self.state.to_json(),
        }
        if self.undo:
            out["undo"] = [list(pair) for pair in self.undo]
        return out

    @classmethod
    def from_json(cls, obj: Any) -> TaskSpec:
        if not isinstance(obj, dict) or not isinstance(obj.get("task"), str):
            raise SpecError("spec: expected an object with a 'task' name")
        state, undo = obj.get("state"), obj.get("undo", [])
        if not isinstance(undo, list) or not all(isinstance(p, list) for p in undo):
            raise SpecError("spec.undo: expected a list of [element, element] pairs")
        return cls(
            task=obj["task"],
            action=ArraySpec.from_json(obj.get("action"), "spec.action"),
            state=None if state is None else ArraySpec.from_json(state, "spec.state"),
            undo=tuple(tuple(pair) for pair in undo),
        )
