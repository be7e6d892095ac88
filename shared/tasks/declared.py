"""Tasks defined by their data: a `task.json` declares the action's fields, nothing else.

A recorded dataset is enough to train, plan and serve: the declaration becomes a `TaskSpec`
(state None) and a `DataTask` is that spec's codecs. What such a task lacks (states, rules, a
simulator) is absent by design, so the methods that would need them raise an error naming
the task. Action JSON is the declared fields nested by their dots: `pick.row` is
`{"pick": {"row": ...}}`, as the built-in tasks write theirs.

task.json (the import format; `lsr data export` writes the same):

    {"name": "towel_folding", "image_size": 64, "frame": 256,
     "action": [{"name": "pick.row", "range": [0, 255], "pixel": "row"}, ...,
                {"name": "height", "categories": ["table", "top"]},
                {"name": "force", "float": [0.0, 5.0], "levels": 101}],
     "settings": {"d_m": 13.5, "w_eps": 0.8, "min_samples": 6}}
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from shared.tasks.base import InvalidActionError, InvalidStateError, Task
from shared.tasks.spec import NULL, ArraySpec, SpecError, TaskSpec
from shared.workcell import Workcell, WorkcellError

Action = tuple[int, ...]  # the stored integers, in the declared order

_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_-]{0,63}$")
_FIELD = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$")
FLOAT_LEVELS = 256  # default levels of a float field (the APN regresses more than 16 values)
SETTINGS = {"d_m": float, "w_eps": float, "min_samples": int}


class DeclarationError(ValueError):
    """A task.json that does not declare a task; the message names the key at fault."""


def _dtype_for(counts: Sequence[int]) -> str:
    """The narrowest signed integer dtype that holds -1 (no action) .. max count - 1."""
    for dtype in ("int8", "int16", "int32"):
        if max(counts) - 1 <= np.iinfo(dtype).max:
            return dtype
    raise DeclarationError(f"a field has {max(counts)} values, more than int32 holds")


def _field_spec(index: int, obj: Any, frame: int | None) -> tuple[str, int, dict, str | None]:
    """(name, count, encoding, pixel axis) of one declared action field."""
    where = f"action[{index}]"
    if not isinstance(obj, dict) or not isinstance(obj.get("name"), str):
        raise DeclarationError(f"{where}: expected an object with a 'name'")
    name = obj["name"]
    where = f"action[{index}] ({name})"
    if not _FIELD.match(name):
        raise DeclarationError(f"{where}: a name is identifiers joined by dots, like pick.row")
    kinds = [k for k in ("range", "categories", "float") if k in obj]
    if len(kinds) != 1:
        raise DeclarationError(f"{where}: give exactly one of range, categories, float")
    allowed = {"name", kinds[0]} | {"range": {"pixel"}, "float": {"levels"}}.get(kinds[0], set())
    unknown = sorted(set(obj) - allowed)
    if unknown:
        raise DeclarationError(f"{where}: unknown key {unknown[0]!r}; allowed: {sorted(allowed)}")
    kind, value = kinds[0], obj[kinds[0]]
    pixel = obj.get("pixel")
    if kind == "range":
        if (
            not isinstance(value, list)
            or len(value) != 2
            or any(isinstance(v, bool) or not isinstance(v, int) for v in value)
            or value[0] > value[1]
        ):
            raise DeclarationError(f"{where}: range must be [low, high], integers, low <= high")
        if pixel is not None:
            if pixel not in ("row", "col"):
                raise DeclarationError(f"{where}: pixel must be 'row' or 'col'")
            if frame is None:
                raise DeclarationError(f"{where}: a pixel field needs the task's 'frame'")
            if value[0] < 0 or value[1] >= frame:
                raise DeclarationError(f"{where}: a pixel range must lie in 0..{frame - 1}")
        encoding = {} if value[0] == 0 else {"low": value[0]}
        return name, value[1] - value[0] + 1, encoding, pixel
    if kind == "categories":
        if (
            not isinstance(value, list)
            or not value
            or not all(isinstance(c, str) and c for c in value)
            or len(set(value)) != len(value)
        ):
            raise DeclarationError(f"{where}: categories must be distinct non-empty strings")
        return name, len(value), {"categories": list(value)}, None
    levels = obj.get("levels", FLOAT_LEVELS)
    if (
        not isinstance(value, list)
        or len(value) != 2
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
        or not all(math.isfinite(v) for v in value)
        or not value[0] < value[1]
    ):
        raise DeclarationError(f"{where}: float must be [low, high], finite, low < high")
    if isinstance(levels, bool) or not isinstance(levels, int) or levels < 2:
        raise DeclarationError(f"{where}: levels must be an integer >= 2")
    return name, levels, {"float": [float(value[0]), float(value[1])]}, None


@dataclass(frozen=True)
class TaskDeclaration:
    """A task.json: the task's spec plus the image size and settings it trains with."""

    spec: TaskSpec
    image_size: int
    settings: dict[str, Any] = field(default_factory=dict)
    # the table's markers: frames are registered to the table frame on import (None: a camera
    # that never moves, images only centre-cropped and resized)
    markers: Workcell | None = None

    @property
    def name(self) -> str:
        return self.spec.task

    @classmethod
    def from_json(cls, obj: Any) -> TaskDeclaration:
        if not isinstance(obj, dict):
            raise DeclarationError("expected a JSON object")
        unknown = sorted(
            set(obj) - {"name", "image_size", "frame", "action", "undo", "settings", "markers"}
        )
        if unknown:
            raise DeclarationError(
                f"unknown key {unknown[0]!r}; a task has name, image_size, frame, action, "
                "undo, settings, markers"
            )
        name = obj.get("name")
        if not isinstance(name, str) or not _NAME.match(name):
            raise DeclarationError(
                "name: 1-64 letters, digits, '_' or '-', starting with a letter or '_'"
            )
        size = obj.get("image_size")
        if isinstance(size, bool) or not isinstance(size, int) or not 16 <= size <= 1024:
            raise DeclarationError("image_size: an integer from 16 to 1024 (pixels, square)")
        if size & (size - 1):
            raise DeclarationError(f"image_size: {size} is not a power of two (64, 128, 256)")
        frame = obj.get("frame")
        if frame is not None and (
            isinstance(frame, bool) or not isinstance(frame, int) or frame < 1
        ):
            raise DeclarationError("frame: a positive integer (pixels of the action's frame)")
        fields = obj.get("action")
        if not isinstance(fields, list) or not fields:
            raise DeclarationError("action: expected a non-empty list of fields")
        parsed = [_field_spec(i, f, frame) for i, f in enumerate(fields)]
        names = [p[0] for p in parsed]
        _check_tree(names)
        counts = [p[1] for p in parsed]
        pixels = {n: axis for n, _, _, axis in parsed if axis is not None}
        try:
            action = ArraySpec(
                dtype=_dtype_for(counts),
                shape=(len(names),),
                names=tuple(names),
                counts=tuple(counts),
                nullable=True,
                pixels=pixels,
                frame=frame if pixels else None,
                encodings={n: e for n, _, e, _ in parsed if e},
            )
        except SpecError as exc:
            raise DeclarationError(str(exc)) from None
        settings = obj.get("settings", {})
        if not isinstance(settings, dict):
            raise DeclarationError("settings: expected an object")
        for key, value in settings.items():
            if key not in SETTINGS:
                raise DeclarationError(f"settings: unknown key {key!r}; known: {sorted(SETTINGS)}")
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise DeclarationError(f"settings.{key}: expected a number")
            if SETTINGS[key] is int and not float(value).is_integer():
                raise DeclarationError(f"settings.{key}: expected an integer")
            if value <= 0 and key != "w_eps":
                raise DeclarationError(f"settings.{key}: must be positive")
        try:
            markers = Workcell.from_json(obj.get("markers"))
        except WorkcellError as exc:
            raise DeclarationError(str(exc)) from None
        undo = obj.get("undo", [])
        if not isinstance(undo, list) or not all(
            isinstance(p, list) and all(isinstance(n, str) for n in p) for p in undo
        ):
            raise DeclarationError("undo: expected a list of [field, field] pairs")
        try:
            spec = TaskSpec(name, action, None, tuple(tuple(p) for p in undo))
        except SpecError as exc:
            raise DeclarationError(str(exc)) from None
        return cls(spec, size, dict(settings), markers)

    @classmethod
    def of_spec(
        cls,
        spec: TaskSpec,
        image_size: int,
        settings: dict[str, Any] | None = None,
        markers: Workcell | None = None,
    ) -> TaskDeclaration:
        """The declaration of any dataset's actions (export writes it); its states are dropped."""
        spec = TaskSpec(spec.task, spec.action, None, spec.undo)
        return cls(spec, image_size, dict(settings or {}), markers)

    def to_json(self) -> dict[str, Any]:
        action = self.spec.action
        if action.start != 0:
            raise DeclarationError(
                f"{self.name}: actions starting at {action.start} not exportable"
            )
        fields = []
        for name, count in zip(action.names, action.counts, strict=True):
            encoding = action.encodings.get(name, {})
            item: dict[str, Any] = {"name": name}
            if "categories" in encoding:
                item["categories"] = list(encoding["categories"])
            elif "float" in encoding:
                item["float"] = list(encoding["float"])
                item["levels"] = count
            else:
                low = int(encoding.get("low", 0))
                item["range"] = [low, low + count - 1]
                if name in action.pixels:
                    item["pixel"] = action.pixels[name]
            fields.append(item)
        out: dict[str, Any] = {"name": self.name, "image_size": self.image_size}
        if action.pixels:
            out["frame"] = action.frame
        out["action"] = fields
        if self.spec.undo:
            out["undo"] = [list(pair) for pair in self.spec.undo]
        if self.settings:
            out["settings"] = dict(self.settings)
        out["markers"] = None if self.markers is None else self.markers.to_json()
        return out


def _check_tree(names: Sequence[str]) -> None:
    """Dotted names must nest into one JSON object: no duplicates, no leaf that is a group."""
    seen = set()
    for name in names:
        if name in seen:
            raise DeclarationError(f"action: field {name!r} declared twice")
        seen.add(name)
    for name in names:
        parts = name.split(".")
        for i in range(1, len(parts)):
            if ".".join(parts[:i]) in seen:
                raise DeclarationError(
                    f"action: {'.'.join(parts[:i])!r} is a field and a group of {name!r}"
                )


class DataTask(Task[None, Action]):
    """Codecs of a declared task: actions in and out, no states, no rules, no world."""

    def __init__(self, spec: TaskSpec, workcell: Workcell | None = None) -> None:
        if spec.state is not None:
            raise SpecError(f"{spec.task}: a data-only task declares no states")
        self.__dict__["workcell"] = workcell  # its data's markers, not a built-in layout
        self.name = spec.task
        self._spec = spec
        self.fields = spec.action.names

    @property
    def spec(self) -> TaskSpec:
        return self._spec

    def _missing(self, what: str) -> str:
        return f"task {self.name!r} is defined by its data: it has no {what}"

    def info(self) -> dict[str, Any]:
        return {
            "task": self.name,
            "declared": True,
            **self.markers_info(),
            "capabilities": {"states": False, "rules": False, "world": False},
            "num_views": None,  # no states to view
            "action_fields": list(self.fields),
            "action_format": self._format(),
            "spec": self.spec.to_json(),
        }

    def _format(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        action = self.spec.action
        for name, count in zip(action.names, action.counts, strict=True):
            encoding = action.encodings.get(name, {})
            if "categories" in encoding:
                text = f"one of {encoding['categories']}"
            elif "float" in encoding:
                low, high = encoding["float"]
                text = f"a number from {low} to {high}"
            else:
                low = int(encoding.get("low", 0))
                text = f"{low}..{low + count - 1}"
                if name in action.pixels:
                    text += f" ({action.pixels[name]} pixel of a {action.frame} px frame)"
            node = out
            *groups, leaf = name.split(".")
            for group in groups:
                node = node.setdefault(group, {})
            node[leaf] = text
        return out

    # ----- actions -----
    def parse_action(self, obj: Any) -> Action:
        values = []
        for i, name in enumerate(self.fields):
            values.append(self._parse_value(i, name, _lookup(obj, name)))
        _refuse_unknown(obj, set(self.fields), "")
        return tuple(values)

    def _parse_value(self, index: int, name: str, value: Any) -> int:
        count = self.spec.action.counts[index]
        encoding = self.spec.action.encodings.get(name, {})
        if "categories" in encoding:
            categories = encoding["categories"]
            if value not in categories or not isinstance(value, str):
                raise InvalidActionError(f"{name}: expected one of {categories}, got {value!r}")
            return categories.index(value)
        if "float" in encoding:
            low, high = encoding["float"]
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise InvalidActionError(f"{name}: expected a number")
            if not (math.isfinite(value) and low <= value <= high):
                raise InvalidActionError(f"{name}: {value} is out of range {low}..{high}")
            return round((value - low) / (high - low) * (count - 1))
        low = int(encoding.get("low", 0))
        if isinstance(value, bool) or not isinstance(value, int):
            raise InvalidActionError(f"{name}: expected an integer")
        if not low <= value < low + count:
            raise InvalidActionError(f"{name}: {value} is out of range {low}..{low + count - 1}")
        return value - low

    def action_to_json(self, action: Action) -> dict[str, Any]:
        out: dict[str, Any] = {}
        action_spec = self.spec.action
        for name, stored, count in zip(self.fields, action, action_spec.counts, strict=True):
            encoding = action_spec.encodings.get(name, {})
            if "categories" in encoding:
                value: Any = encoding["categories"][int(stored)]
            elif "float" in encoding:
                low, high = encoding["float"]
                value = low + (high - low) * int(stored) / (count - 1)
            else:
                value = int(stored) + int(encoding.get("low", 0))
            node = out
            *groups, leaf = name.split(".")
            for group in groups:
                node = node.setdefault(group, {})
            node[leaf] = value
        return out

    def action_to_array(self, action: Action | None) -> np.ndarray:
        if action is None:
            return np.full(self.spec.action.shape, NULL, dtype=self.spec.action.dtype)
        return np.asarray(action, dtype=self.spec.action.dtype).reshape(self.spec.action.shape)

    def array_to_action(self, array: np.ndarray) -> Action | None:
        flat = np.asarray(array).reshape(-1)
        if (flat == NULL).all():
            return None
        return tuple(int(v) for v in flat)

    # ----- what a data-only task does not have -----
    def check_action(self, state: None, action: Action) -> None:
        raise NotImplementedError(self._missing("rules"))

    def legal_actions(self, state: None) -> list[Action]:
        raise NotImplementedError(self._missing("rules"))

    def _apply_legal(self, state: None, action: Action) -> None:
        raise NotImplementedError(self._missing("rules"))

    def parse_state(self, obj: Any) -> None:
        raise InvalidStateError(self._missing("states; give an image instead"))

    def state_to_json(self, state: None) -> dict[str, Any]:
        raise NotImplementedError(self._missing("states"))

    def state_to_array(self, state: None) -> np.ndarray:
        raise NotImplementedError(self._missing("states"))

    def array_to_state(self, array: np.ndarray) -> None:
        raise NotImplementedError(self._missing("states"))


def _lookup(obj: Any, name: str) -> Any:
    node, path = obj, []
    for part in name.split("."):
        if not isinstance(node, dict):
            where = ".".join(path) or "action"
            raise InvalidActionError(f"{where}: expected an object with {part!r}")
        if part not in node:
            raise InvalidActionError(f"{'.'.join([*path, part])}: missing")
        node = node[part]
        path.append(part)
    return node


def _refuse_unknown(obj: Any, names: set[str], prefix: str) -> None:
    for key, value in obj.items():
        path = f"{prefix}{key}"
        if path in names:
            continue
        if isinstance(value, dict) and any(n.startswith(path + ".") for n in names):
            _refuse_unknown(value, names, path + ".")
            continue
        raise InvalidActionError(f"{path}: unknown field; the action has {sorted(names)}", key=path)
