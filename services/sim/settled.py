"""Settled-state libraries: every state of a deformable world reached once by physics, then loaded.

Folding a cloth into a state costs about a second of MuJoCo a fold; loading the vertices it
settled at costs microseconds. A library holds one settled physics state (positions and
velocities) per move order that resets use, for every state. Orders share their prefixes (the
prefix of an order is an order of a smaller state), so each prefix is folded once, from its
parent's settled state. It is keyed by the world's scene hash (MJCF, motion recipe, moves,
MuJoCo version): a changed scene never loads stale states. Stored as safetensors beside a JSON
index, written to a folder beside the target and moved in place, and sealed like model parts.

A world missing from every library folder fills its library on first use, order by order, in
memory; `lsr sim settle` (and the sim service at start) builds the whole library and saves it.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from collections.abc import Hashable, Iterable, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from safetensors.numpy import load_file, save_file
from tqdm import tqdm

from shared.checkpoint import CheckpointError, read_versioned_json, seal, verify
from shared.settings import MODELS_DIR
from shared.tasks.base import Task, WorldError

log = logging.getLogger(__name__)

FORMAT = "lsr-settled"
VERSION = 1
INDEX = "library.json"
STATES = "states.safetensors"
FOLDER = "settled"  # a model folder's library: MODEL/settled


class Settling(Protocol):
    """What a world provides to have its resets served from a library."""

    task: Task

    def scene_hash(self) -> str:
        """Changes whenever anything that shapes a settled state changes."""
        ...

    def reset_orders(self, state: Hashable) -> list[tuple[Any, ...]]:
        """The action sequences from the origin state that reach `state`, as resets use them."""
        ...

    def place_origin(self) -> None:
        """The origin state (the flat cloth), exactly, without noise."""
        ...

    def act(self, action: Any) -> None:
        """Carry out a canonical action physically (no rule check: the order is legal)."""
        ...

    def read_state(self) -> Any: ...

    def physics_state(self) -> np.ndarray: ...

    def load_physics_state(self, physics: np.ndarray) -> None: ...


def cache_dir() -> Path:
    """Where built libraries are kept: $LSR_CACHE_DIR, else ~/.cache/lsr."""
    return Path(os.environ.get("LSR_CACHE_DIR") or Path.home() / ".cache" / "lsr")


def default_folders() -> list[Path]:
    """Library folders searched by default: each shipped model's, then the cache's."""
    shipped = sorted(MODELS_DIR.glob(f"*/{FOLDER}")) if MODELS_DIR.is_dir() else []
    cached = sorted((cache_dir() / FOLDER).glob("*"))
    return [*shipped, *cached]


Order = tuple[Any, ...]


class SettledLibrary:
    """Settled physics states of one scene, by move order; filled on demand, saved whole."""

    def __init__(self, task: Task, scene_hash: str, source: Path | None = None) -> None:
        self.task = task
        self.scene_hash = scene_hash
        self.source = source  # the folder it was loaded from; None: built in this process
        self.physics: dict[Order, np.ndarray] = {}
        self.build_seconds = 0.0  # physics spent filling it in this process

    # ----- use -----
    def variant(self, world: Settling, order: Order) -> np.ndarray:
        """The settled physics state after `order`, folded now if the library lacks it."""
        if order not in self.physics:
            started = time.perf_counter()
            if order:
                parent = self.variant(world, order[:-1])
                world.load_physics_state(parent)
                world.act(order[-1])
            else:
                world.place_origin()
            expected = self.state_after(order)
            if world.read_state() != expected:
                raise WorldError(
                    f"settling {self.task.state_to_json(expected)}: the cloth reads as "
                    f"{self.task.state_to_json(world.read_state())}"
                )
            self.physics[order] = world.physics_state()
            self.build_seconds += time.perf_counter() - started
        return self.physics[order]

    def state_after(self, order: Order) -> Any:
        """The state an order reaches from the origin, the task's first state (the flat cloth)."""
        state = self.task.all_states()[0]
        for action in order:
            state = self.task.apply(state, action)
        return state

    def orders(self, world: Settling) -> list[Order]:
        """Every order of every state, each after its prefixes."""
        found: set[Order] = set()
        for state in self.task.all_states():
            for order in world.reset_orders(state):
                found.update(order[:k] for k in range(len(order) + 1))
        return sorted(found, key=_order_key)

    def complete(self, world: Settling) -> bool:
        return all(order in self.physics for order in self.orders(world))

    def fill(self, world: Settling, progress: bool = True) -> SettledLibrary:
        """Fold every order the library lacks (a progress bar shows them)."""
        missing = [o for o in self.orders(world) if o not in self.physics]
        bar = tqdm(
            missing, desc=f"settling {self.task.name} states", unit="state", disable=not progress
        )
        for order in bar:
            self.variant(world, order)
        return self

    # ----- storage -----
    def save(self, folder: Path | str) -> Path:
        """Write `folder` (index, states, manifest) beside it, then move it in place."""
        folder = Path(folder)
        orders = sorted(self.physics, key=_order_key)
        partial = folder.with_name(f".{folder.name}.{os.getpid()}.partial")
        shutil.rmtree(partial, ignore_errors=True)
        partial.mkdir(parents=True)
        save_file({"physics": np.stack([self.physics[o] for o in orders])}, partial / STATES)
        os.chmod(partial / STATES, 0o644)  # safetensors writes it private; others read it
        index = {
            "format": FORMAT,
            "version": VERSION,
            "task": self.task.name,
            "scene_hash": self.scene_hash,
            "orders": [[self.task.action_to_json(a) for a in o] for o in orders],
            "states": [self.task.state_to_json(self.state_after(o)) for o in orders],
            "build_seconds": round(self.build_seconds, 1),
        }
        (partial / INDEX).write_text(json.dumps(index, indent=1) + "\n")
        seal(partial, [INDEX, STATES])
        if folder.exists():  # a library of the same scene: the new one replaces it whole
            old = folder.with_name(f".{folder.name}.{os.getpid()}.old")
            os.replace(folder, old)
            os.replace(partial, folder)
            shutil.rmtree(old, ignore_errors=True)
        else:
            folder.parent.mkdir(parents=True, exist_ok=True)
            os.replace(partial, folder)
        self.source = folder
        return folder

    @classmethod
    def load(cls, folder: Path | str, task: Task) -> SettledLibrary:
        """A saved library, checked against its manifest; CheckpointError names what is wrong."""
        folder = Path(folder)
        if not verify(folder):
            raise CheckpointError(f"{folder}: not sealed (no MANIFEST.json)")
        index = read_versioned_json(folder / INDEX, FORMAT, VERSION, "a settled-state library")
        if index.get("task") != task.name:
            raise CheckpointError(f"{folder / INDEX}: task {index.get('task')!r}, not {task.name}")
        physics = load_file(str(folder / STATES))["physics"]
        orders = [tuple(task.parse_action(a) for a in o) for o in index["orders"]]
        if len(orders) != len(physics):
            raise CheckpointError(f"{folder}: {len(orders)} orders but {len(physics)} states")
        library = cls(task, index["scene_hash"], source=folder)
        library.physics = dict(zip(orders, physics, strict=True))
        return library

    @classmethod
    def find(
        cls, task: Task, scene_hash: str, folders: Iterable[Path] | None = None
    ) -> SettledLibrary:
        """The first library of this scene among `folders` (default: shipped, then cached);
        an empty one, to fill on demand, when none has it."""
        for folder in default_folders() if folders is None else folders:
            index = folder / INDEX
            try:
                if json.loads(index.read_text()).get("scene_hash") != scene_hash:
                    continue
                return cls.load(folder, task)
            except (OSError, ValueError) as exc:  # unreadable or unsealed: skipped, and said
                log.warning("settled-state library %s skipped: %s", folder, exc)
        return cls(task, scene_hash)


def _order_key(order: Order) -> tuple[int, list[str]]:
    """Shorter orders first (each after its prefixes), then a fixed order among equals."""
    return len(order), [str(a) for a in order]


def cached_folder(scene_hash: str) -> Path:
    return cache_dir() / FOLDER / scene_hash[:16]


def ensure_complete(
    world: Settling, library: SettledLibrary, progress: bool = True, save_to: Path | None = None
) -> SettledLibrary:
    """Build what `library` lacks and save it (default: in the cache), so that later
    processes load it; a complete library is returned as it is."""
    if library.complete(world):
        return library
    log.info("building the settled-state library of %s (scene %s)", library.task.name,
             library.scene_hash[:16])  # fmt: skip
    library.fill(world, progress)
    library.save(save_to or cached_folder(library.scene_hash))
    return library


def stored_orders(library: SettledLibrary, state: Any) -> Sequence[Order]:
    """The orders stored for `state` (tests and reports)."""
    return [o for o in library.physics if library.state_after(o) == state]
