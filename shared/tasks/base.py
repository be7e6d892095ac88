"""Task-agnostic interfaces: the logic of a manipulation task and the physical world that runs it.

A `Task` is pure logic (states, actions, legality) that every service can use without MuJoCo.
A `World` is the simulated physics of the same task (render, execute, read back); the sim
service owns the implementations. A second task (cloth folding) plugs in by implementing both.
"""

from __future__ import annotations

import copy
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Hashable, Mapping, Sequence
from functools import cached_property
from typing import Any, ClassVar, Generic, TypeVar

import numpy as np

from shared.tasks.spec import TaskSpec
from shared.workcell import Workcell, load_workcell

State = TypeVar("State")
Action = TypeVar("Action")


class TaskError(ValueError):
    """Bad input for a task; the message names what is wrong, `key` the offending key of the
    object given (an unknown key, say), so that callers can point at it."""

    def __init__(self, message: str, key: str | None = None) -> None:
        super().__init__(message)
        self.key = key


class InvalidStateError(TaskError):
    """A state that the task cannot be in (unknown box, column too high, ...)."""


class InvalidActionError(TaskError):
    """An action that is malformed (missing field, out-of-range cell, ...)."""


class IllegalActionError(TaskError):
    """A well-formed action that breaks a rule of the task in the given state."""


def state_field(obj: Any, key: str, what: str) -> Any:
    """`obj[key]` of a state object `{key: ...}`, refusing other shapes and unknown keys."""
    if not isinstance(obj, dict) or key not in obj:
        got = f" (got keys {sorted(obj, key=str)})" if isinstance(obj, dict) else ""
        raise InvalidStateError(f"state: expected an object with a '{key}' {what}{got}")
    extra = sorted(set(obj) - {key}, key=str)
    if extra:
        raise InvalidStateError(
            f"state: unknown key {extra[0]!r}; a state has only '{key}'", key=str(extra[0])
        )
    return obj[key]


def parse_row_col(obj: Any, field: str, rows: int, cols: int) -> tuple[int, int]:
    """`{"row": R, "col": C}` with 0 <= R < rows and 0 <= C < cols (a grid cell or a pixel);
    InvalidActionError naming `field` and the coordinate otherwise."""
    if not isinstance(obj, dict) or set(obj) != {"row", "col"}:
        raise InvalidActionError(f"{field}: expected an object with 'row' and 'col'")
    values = []
    for coord, limit in (("row", rows), ("col", cols)):
        v = obj[coord]
        if isinstance(v, bool) or not isinstance(v, int):
            raise InvalidActionError(f"{field}.{coord}: expected an integer")
        if not 0 <= v < limit:
            raise InvalidActionError(f"{field}.{coord}: {v} is out of range 0..{limit - 1}")
        values.append(v)
    return values[0], values[1]


class WorldError(RuntimeError):
    """The physical world reached something it cannot read back as a valid state."""


class Task(ABC, Generic[State, Action]):
    """States, actions and rules of one task, with array codecs for datasets; and the facts
    generic code asks a task for, never naming one."""

    name: str
    # The paper's d_m per latent metric (the action term's minimum distance), about the mean
    # action-pair distance under the baseline VAE; a task the paper did not study gets box
    # stacking's values.
    d_m: ClassVar[Mapping[str, float]] = {"l1": 20.0, "l2": 5.0, "inf": 2.5}
    # Roadmap settings (eps_rule, w_eps, min_samples, keep_rare) measured for the task where
    # the defaults do not hold; a dataset's task.json settings and flags come first.
    roadmap_settings: ClassVar[Mapping[str, Any]] = {}
    # The look (shared.appearance level) its data and renders take when none is asked for.
    default_look: ClassVar[str] = "clean"
    # Its simulated world, "module:Class" imported on first use (as Gymnasium's entry points);
    # None for a task known only from its data.
    world_entry: ClassVar[str | None] = None

    def state_label(self, state: State) -> str:
        """A short text of a state, for contact sheets."""
        return str(self.state_to_json(state))

    def action_label(self, action: Action) -> str:
        """A short text of an action, for contact sheets: its pick and release (and grasp
        height) where it has them, else its JSON."""
        pick, release = getattr(action, "pick", None), getattr(action, "release", None)
        if pick is None or release is None:
            return str(self.action_to_json(action))
        text = f"({pick.row},{pick.col})->({release.row},{release.col})"
        return text + (f" h{action.height}" if hasattr(action, "height") else "")

    @abstractmethod
    def info(self) -> dict[str, Any]:
        """JSON description published by `lsr task info` and `GET /tasks/{name}`."""

    # --- JSON codecs (the public interface) ---
    @abstractmethod
    def parse_state(self, obj: Any) -> State:
        """Validate a JSON state; raises InvalidStateError naming what is wrong."""

    @abstractmethod
    def state_to_json(self, state: State) -> dict[str, Any]: ...

    @abstractmethod
    def parse_action(self, obj: Any) -> Action:
        """Validate a JSON action's form; raises InvalidActionError naming the field."""

    @abstractmethod
    def action_to_json(self, action: Action) -> dict[str, Any]: ...

    # --- rules ---
    @abstractmethod
    def check_action(self, state: State, action: Action) -> None:
        """Raise IllegalActionError naming the broken rule, or return when legal."""

    @abstractmethod
    def legal_actions(self, state: State) -> list[Action]: ...

    def apply(self, state: State, action: Action) -> State:
        """The successor state; raises IllegalActionError for an illegal action."""
        self.check_action(state, action)
        return self._apply_legal(state, action)

    @abstractmethod
    def _apply_legal(self, state: State, action: Action) -> State: ...

    def neighbours(self, state: State) -> list[tuple[Action, State]]:
        return [(a, self._apply_legal(state, a)) for a in self.legal_actions(state)]

    @cached_property
    def workcell(self) -> Workcell | None:
        """The markers on this task's table (None: a camera that never moves, nothing to
        register)."""
        return load_workcell(self.name)

    def markers_info(self) -> dict[str, Any]:
        """The workcell's part of `info()`: the markers, or null (registration off)."""
        return {"markers": None if self.workcell is None else self.workcell.to_json()}

    def with_workcell(self, workcell: Workcell | None) -> Task[State, Action]:
        """This task on a table with other markers (None: none): a world of it renders
        them, which is how a workcell is designed and measured."""
        other = copy.copy(self)
        other.__dict__["workcell"] = workcell  # tasks are frozen; the property is cached here
        return other

    def hidden(self, state: State) -> frozenset[str]:
        """Parts of a state that its images cannot show (none for most tasks): evaluations
        report plans between states that show everything apart from the rest."""
        return frozenset()

    def view(self, state: State) -> Hashable:
        """What a camera above shows of `state`: the state itself for most tasks; a task with
        hidden parts (`hidden`) maps the states that look alike to one view."""
        return state

    def num_views(self) -> int | None:
        """How many views the states give (None: the states cannot be enumerated)."""
        states = self.all_states()
        return None if states is None else len({self.view(s) for s in states})

    def view_to_json(self, state: State) -> dict[str, Any]:
        """The JSON of `view(state)`: the state's own where nothing hides; a task with hidden
        parts names them, so that a viewer can draw them as unknown."""
        return self.state_to_json(state)

    def sample_state(self, rng: np.random.Generator) -> State:
        """A state drawn uniformly; tasks that cannot enumerate their states override this."""
        states = self.all_states()
        if states is None:
            raise NotImplementedError(f"{self.name}: no all_states() to sample from")
        return states[int(rng.integers(len(states)))]

    def all_states(self) -> Sequence[State] | None:
        """Every state, for tasks small enough to enumerate; None otherwise."""
        return None

    def state_index(self, state: State) -> int:
        """Position of `state` in `all_states()`: a class label for evaluation."""
        return self._state_indices[state]

    @cached_property
    def _state_indices(self) -> dict[State, int]:
        return {s: i for i, s in enumerate(self.all_states() or ())}

    # --- fixed-shape array codecs (datasets, evaluation), described by `spec` ---
    @property
    @abstractmethod
    def spec(self) -> TaskSpec:
        """dtype, shape and value range of the action and state arrays."""

    @abstractmethod
    def state_to_array(self, state: State) -> np.ndarray: ...

    @abstractmethod
    def array_to_state(self, array: np.ndarray) -> State: ...

    @abstractmethod
    def action_to_array(self, action: Action | None) -> np.ndarray:
        """Array of `spec.action`; None (no action) encodes as all -1."""

    @abstractmethod
    def array_to_action(self, array: np.ndarray) -> Action | None: ...

    def same_action(self, first: np.ndarray, second: np.ndarray) -> bool:
        """Whether two action arrays ask for the same thing: how experience finds an edge it
        contradicts. Equality, unless the task knows how far a click may stray."""
        return bool(np.array_equal(first, second))


class World(ABC, Generic[State, Action]):
    """A physical instance of a task: set a state, look at it, act on it."""

    task: Task[State, Action]
    image_size: int
    # Tuples a data-generation walk makes from one reset: 1 when resetting is cheap; more when
    # reaching a state costs physics (a folded cloth), so that resets do not dominate.
    episode_length: int = 1
    # Worlds whose states cost physics to reach (a folded cloth) reset from a settled-state
    # library (`services.sim.settled`) and take the folders to search as a `library` option.
    settles: bool = False
    # Where its workcell's markers go (`services.sim.workcell.layout`), in canonical pixels:
    # (id, centre, width there), round the view, clear of its edge by their white margin,
    # inside the frame at `shifted` camera draws; and how many registration needs at least.
    marker_places: ClassVar[tuple[tuple[int, tuple[float, float], float], ...]] = ()
    min_markers: ClassVar[int] = 3
    # The highest anything of the scene stands above the table (m): a moved camera is bounded by
    # the parallax it gives there (`Workcell.relief_mm`); 0 for what lies flat (a cloth, a shirt).
    relief_m: float = 0.0

    @abstractmethod
    def reset(self, state: State, rng: np.random.Generator) -> State:
        """Place the objects of `state` with in-cell noise, settle, return the read-back state."""

    @abstractmethod
    def render(self) -> np.ndarray:
        """The current scene in the canonical view, as uint8 (image_size, image_size, 3)."""

    def frame(self) -> np.ndarray:
        """What the cell's camera sees: the canonical view's surroundings with the table's
        markers (`shared.workcell`), at the frame's own size; a world without markers has
        nothing more to show than its render."""
        return self.render()

    @abstractmethod
    def read_state(self) -> State:
        """The state as the physics has it now; raises WorldError when it is not valid."""

    @abstractmethod
    def execute(self, action: Action, rng: np.random.Generator) -> State:
        """Carry out `action` physically and return the read-back state.

        An illegal action raises IllegalActionError and leaves the world unchanged.
        """

    def action_pixels(self, action: Action) -> tuple[tuple[float, float], tuple[float, float]]:
        """Where `action` picks and releases in the rendered image, as (x, y) pixels."""
        raise NotImplementedError(f"{type(self).__name__} does not locate actions in its images")

    def perturb(self, rng: np.random.Generator) -> State:
        """The same state looking slightly different (a no-action pair's second image).

        By default the state is placed again with fresh noise.
        """
        return self.reset(self.read_state(), rng)

    def demonstrated(self, action: Action, rng: np.random.Generator) -> Action:
        """`action` as a demonstrator would give it (a few pixels off for clicks); exact here."""
        return action

    def close(self) -> None:
        """Release rendering resources."""

    def __enter__(self) -> World[State, Action]:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def optimal_moves(task: Task, start: Any, goal: Any, by_state: bool = False) -> int | None:
    """Fewest moves from `start` to a state that shows `goal`'s view (`Task.view`), or to
    `goal` itself with `by_state`: breadth-first search over the task's state graph."""
    target = goal if by_state else task.view(goal)
    seen = {start: 0}
    queue = deque([start])
    while queue:
        state = queue.popleft()
        if (state if by_state else task.view(state)) == target:
            return seen[state]
        for _, nxt in task.neighbours(state):
            if nxt not in seen:
                seen[nxt] = seen[state] + 1
                queue.append(nxt)
    return None
