"""Box stacking (paper section VI-A): 4 distinct boxes on a grid of 3 columns x 3 levels.

A state lists, per column from left to right, the box ids from the table upwards. An action
moves the top box of one column onto the top of another column.
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

Stacks = tuple[tuple[str, ...], ...]


class Cell(NamedTuple):
    row: int  # level counted from the table, 0 = standing on the table
    col: int  # column, 0 = leftmost in the image


class Move(NamedTuple):
    pick: Cell
    release: Cell


@dataclass(frozen=True)
class BoxStackingConfig:
    boxes: tuple[str, ...] = ("red", "green", "blue", "yellow")
    columns: int = 3
    levels: int = 3


@dataclass(frozen=True)
class BoxStacking(Task[Stacks, Move]):
    config: BoxStackingConfig = field(default_factory=BoxStackingConfig)
    name: str = "box_stacking"
    world_entry = "services.sim.box_stacking.world:BoxStackingWorld"

    def state_label(self, state: Stacks) -> str:
        """Each column's boxes bottom up by initial, '-' for an empty one: 'R,G | B | -'."""
        return " | ".join(",".join(b[0].upper() for b in c) or "-" for c in state)

    # ----- description -----
    def info(self) -> dict[str, Any]:
        c = self.config
        return {
            "task": self.name,
            "boxes": list(c.boxes),
            **self.markers_info(),
            "columns": c.columns,
            "levels": c.levels,
            "num_states": len(self.all_states()),
            "num_views": self.num_views(),  # every state is its own view
            "num_transitions": sum(len(self.legal_actions(s)) for s in self.all_states()),
            "state_format": {"stacks": "one list per column (left to right), box ids bottom-up"},
            "action_format": {
                "pick": {"row": "level of the top box of the pick column", "col": "0..columns-1"},
                "release": {"row": "current height of the release column", "col": "0..columns-1"},
            },
            "spec": self.spec.to_json(),
        }

    @cached_property
    def spec(self) -> TaskSpec:  # type: ignore[override]
        c = self.config
        cells = [(r, col) for r in range(c.levels) for col in range(c.columns)]
        return TaskSpec(
            task=self.name,
            action=ArraySpec(
                dtype="int8",
                shape=(4,),
                names=("pick.row", "pick.col", "release.row", "release.col"),
                counts=(c.levels, c.columns, c.levels, c.columns),
                nullable=True,
            ),
            # [level, column] -> index of the box in `boxes`, -1 = empty
            state=ArraySpec(
                dtype="int8",
                shape=(c.levels, c.columns),
                names=tuple(f"cell[{r}][{col}]" for r, col in cells),
                counts=(len(c.boxes) + 1,) * len(cells),
                start=-1,
            ),
            # The moved box is the top of its new column and its old cell is free again
            undo=(("pick.row", "release.row"), ("pick.col", "release.col")),
        )

    # ----- JSON codecs -----
    def parse_state(self, obj: Any) -> Stacks:
        c = self.config
        stacks = state_field(obj, "stacks", "list")
        if not isinstance(stacks, list | tuple):
            raise InvalidStateError("state.stacks: expected a list of columns")
        if len(stacks) != c.columns:
            raise InvalidStateError(
                f"state.stacks: expected {c.columns} columns, got {len(stacks)}"
            )
        seen: set[str] = set()
        for i, column in enumerate(stacks):
            if not isinstance(column, list | tuple):
                raise InvalidStateError(f"state.stacks[{i}]: expected a list of box ids")
            if len(column) > c.levels:
                raise InvalidStateError(
                    f"state.stacks[{i}]: {len(column)} boxes, a column holds at most {c.levels}"
                )
            for j, box in enumerate(column):
                if not isinstance(box, str) or box not in c.boxes:
                    raise InvalidStateError(
                        f"state.stacks[{i}][{j}]: unknown box id {box!r}; "
                        f"known ids are {list(c.boxes)}"
                    )
                if box in seen:
                    raise InvalidStateError(f"state.stacks[{i}][{j}]: box {box!r} appears twice")
                seen.add(box)
        missing = [b for b in c.boxes if b not in seen]
        if missing:
            raise InvalidStateError(f"state.stacks: missing boxes {missing}")
        return tuple(tuple(column) for column in stacks)

    def state_to_json(self, state: Stacks) -> dict[str, Any]:
        return {"stacks": [list(column) for column in state]}

    def parse_action(self, obj: Any) -> Move:
        if not isinstance(obj, dict):
            raise InvalidActionError("action: expected an object with 'pick' and 'release'")
        c = self.config
        pick, release = (
            Cell(*parse_row_col(obj.get(key), f"action.{key}", c.levels, c.columns))
            for key in ("pick", "release")
        )
        return Move(pick, release)

    def action_to_json(self, action: Move) -> dict[str, Any]:
        return {
            "pick": {"row": action.pick.row, "col": action.pick.col},
            "release": {"row": action.release.row, "col": action.release.col},
        }

    # ----- rules -----
    def check_action(self, state: Stacks, action: Move) -> None:
        pick, release = action
        if pick.col == release.col:
            raise IllegalActionError(
                f"pick and release are in the same column {pick.col}: a move changes column"
            )
        height = len(state[pick.col])
        if height == 0:
            raise IllegalActionError(f"pick column {pick.col} is empty: nothing to pick")
        if pick.row != height - 1:
            raise IllegalActionError(
                f"pick row {pick.row} is not the top of column {pick.col} (top box at row "
                f"{height - 1}): only a box with nothing on it can be picked"
            )
        target = len(state[release.col])
        if target >= self.config.levels:
            raise IllegalActionError(
                f"release column {release.col} is full ({target} boxes): no free cell"
            )
        if release.row != target:
            raise IllegalActionError(
                f"release row {release.row} is not the free cell of column {release.col} "
                f"(row {target}): a box is released on the table or on top of another box"
            )

    def legal_actions(self, state: Stacks) -> list[Move]:
        moves = []
        for src, column in enumerate(state):
            if not column:
                continue
            for dst, target in enumerate(state):
                if dst != src and len(target) < self.config.levels:
                    moves.append(Move(Cell(len(column) - 1, src), Cell(len(target), dst)))
        return moves

    def _apply_legal(self, state: Stacks, action: Move) -> Stacks:
        columns = [list(column) for column in state]
        box = columns[action.pick.col].pop()
        columns[action.release.col].append(box)
        return tuple(tuple(column) for column in columns)

    def all_states(self) -> tuple[Stacks, ...]:
        return self._all_states

    @cached_property
    def _all_states(self) -> tuple[Stacks, ...]:
        c = self.config
        n = len(c.boxes)
        heights = [
            h for h in itertools.product(range(c.levels + 1), repeat=c.columns) if sum(h) == n
        ]
        states = []
        for h in heights:
            for order in itertools.permutations(c.boxes):
                cuts = np.cumsum((0, *h))
                states.append(tuple(tuple(order[cuts[i] : cuts[i + 1]]) for i in range(len(h))))
        return tuple(sorted(states))

    # ----- array codecs -----
    def state_to_array(self, state: Stacks) -> np.ndarray:
        grid = np.full(self.spec.state.shape, -1, dtype=np.int8)
        for col, column in enumerate(state):
            for row, box in enumerate(column):
                grid[row, col] = self.config.boxes.index(box)
        return grid

    def array_to_state(self, array: np.ndarray) -> Stacks:
        grid = np.asarray(array)
        if grid.shape != self.spec.state.shape:
            raise InvalidStateError(f"state array: shape {grid.shape} != {self.spec.state.shape}")
        stacks = []
        for col in range(self.config.columns):
            column = []
            for row in range(self.config.levels):
                idx = int(grid[row, col])
                if idx < 0:
                    break
                if idx >= len(self.config.boxes):
                    raise InvalidStateError(f"state array: box index {idx} out of range")
                column.append(self.config.boxes[idx])
            stacks.append(column)
        return self.parse_state({"stacks": stacks})

    def action_to_array(self, action: Move | None) -> np.ndarray:
        if action is None:
            return np.full(4, -1, dtype=np.int8)
        return np.array([*action.pick, *action.release], dtype=np.int8)

    def array_to_action(self, array: np.ndarray) -> Move | None:
        values = [int(v) for v in np.asarray(array).reshape(-1)]
        if all(v < 0 for v in values):
            return None
        return Move(Cell(values[0], values[1]), Cell(values[2], values[3]))
