"""Experience: what a robot or the simulator saw and did, appended to a dataset folder.

An experience folder is a dataset (`shared.dataset`) that grows: each append writes one new
shard and then the manifest that lists it, both through a temporary file and a rename, under an
exclusive lock. A process killed mid-append leaves the folder as it was before (at worst a shard
file that no manifest lists, which the next append overwrites), so nothing already recorded is
ever lost or half-read. `lsr roadmap grow` reads it like any dataset.
"""

from __future__ import annotations

import fcntl
import json
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from shared import dataset as ds
from shared.checkpoint import replace_atomically
from shared.tasks.base import Task
from shared.tasks.spec import TaskSpec

LOCK = ".lock"


class ExperienceError(ValueError):
    """An experience folder that holds something else, or tuples that do not fit it."""


class ExperienceLog:
    """An experience folder for one task, spec and image size; made on first use."""

    def __init__(
        self, directory: Path | str, spec: TaskSpec, image_size: int, source: str = "sim"
    ) -> None:
        self.directory = Path(directory)
        self.spec = spec
        self.image_size = image_size
        self.source = source
        self.directory.mkdir(parents=True, exist_ok=True)
        with self._locked():
            if (self.directory / "manifest.json").is_file():
                self._check(ds.read_manifest(self.directory))

    def _check(self, manifest: dict[str, Any]) -> None:
        """An existing folder must be an experience folder (never a training set) of this
        task's tuples of this spec and size."""
        if "experience" not in manifest:
            raise ExperienceError(
                f"{self.directory}: a dataset, not an experience folder; experience is never "
                "appended to one"
            )
        if ds.manifest_spec(manifest) != self.spec or manifest["image_size"] != self.image_size:
            raise ExperienceError(
                f"{self.directory}: holds {manifest['task']!r} experience at "
                f"{manifest['image_size']} px with another spec; this log records "
                f"{self.spec.task!r} at {self.image_size} px (another model's?); record into "
                "another folder"
            )

    @contextmanager
    def _locked(self) -> Iterator[None]:
        with open(self.directory / LOCK, "a") as handle:
            fcntl.flock(handle, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(handle, fcntl.LOCK_UN)

    def _empty_manifest(self) -> dict[str, Any]:
        return {
            "format": ds.FORMAT,
            "version": ds.VERSION,
            "task": self.spec.task,
            "spec": self.spec.to_json(),
            "image_size": self.image_size,
            "seed": None,
            "experience": {"source": self.source},
            "counts": {"tuples": 0, "action_pairs": 0, "no_action_pairs": 0},
            "shards": [],
        }

    def append(
        self,
        image1: np.ndarray,
        image2: np.ndarray,
        u: np.ndarray,
        state1: np.ndarray | None = None,
        state2: np.ndarray | None = None,
    ) -> int:
        """Record tuples (a no-action pair has u = -1 everywhere); the tuples now recorded.

        States go with them where the recorder knows them (the simulator does); a folder whose
        spec has no states takes none.
        """
        u = np.asarray(u, dtype=self.spec.action.dtype)
        n = len(u)
        arrays = {
            "image1": np.asarray(image1, np.uint8),
            "image2": np.asarray(image2, np.uint8),
            "a": (u.reshape(n, -1) >= 0).any(axis=1).astype(np.uint8),
            "u": u,
        }
        size = (n, self.image_size, self.image_size, 3)
        for name in ("image1", "image2"):
            if arrays[name].shape != size:
                raise ExperienceError(f"{name}: expected shape {size}, got {arrays[name].shape}")
        if self.spec.state is None:
            arrays["state1"] = arrays["state2"] = np.zeros((n, 0), np.int8)
        elif state1 is None or state2 is None:
            raise ExperienceError(f"{self.directory}: this folder records states; give both")
        else:
            arrays["state1"], arrays["state2"] = np.asarray(state1), np.asarray(state2)
        if n == 0:
            return self.count()
        with self._locked():
            path = self.directory / "manifest.json"
            manifest = ds.read_manifest(self.directory) if path.is_file() else None
            manifest = manifest or self._empty_manifest()
            self._check(manifest)
            name = ds.shard_name(len(manifest["shards"]))
            digest: list[str] = []
            replace_atomically(
                self.directory / name,
                lambda tmp: digest.append(ds.write_shard(tmp, arrays, self.spec)),
            )
            manifest["shards"].append({"file": name, "count": n, "sha256": digest[0]})
            counts = manifest["counts"]
            counts["tuples"] += n
            counts["action_pairs"] += int(arrays["a"].sum())
            counts["no_action_pairs"] = counts["tuples"] - counts["action_pairs"]
            text = json.dumps(manifest, indent=2, sort_keys=True) + "\n"
            replace_atomically(path, lambda tmp: tmp.write_text(text))
            return counts["tuples"]

    def count(self) -> int:
        path = self.directory / "manifest.json"
        return ds.read_manifest(self.directory)["counts"]["tuples"] if path.is_file() else 0


def has_experience(directory: Path | str) -> bool:
    """A folder some log has written tuples to."""
    path = Path(directory) / "manifest.json"
    return path.is_file() and bool(ds.read_manifest(directory)["shards"])


# What a closed loop calls after each action: (image, action or None, image after, state,
# state after); the states are None where the recorder does not know them (a real robot).
Record = Callable[[np.ndarray, Any, np.ndarray, Any, Any], object]


class Recorder:
    """What a closed loop saw and did, appended to a log in batches of `batch` tuples (one
    shard each); `flush` at the end. Called as record(image, action, image after, state,
    state after), the action None for a re-observation of an unchanged scene."""

    def __init__(self, log: ExperienceLog, task: Task, batch: int = 200) -> None:
        self.log, self.task, self.batch = log, task, batch
        self.rows: list[tuple[np.ndarray, np.ndarray, np.ndarray, Any, Any]] = []
        self.recorded = 0

    def __call__(
        self, before: np.ndarray, action: Any, after: np.ndarray, state: Any, state_after: Any
    ) -> None:
        self.rows.append((before, action, after, state, state_after))
        if len(self.rows) >= self.batch:
            self.flush()

    def flush(self) -> None:
        if not self.rows:
            return
        image1, image2, u, *states = tuple_arrays(self.task, self.rows)
        self.log.append(image1, image2, u, *(states if self.log.spec.state is not None else ()))
        self.recorded += len(self.rows)
        self.rows = []


def tuple_arrays(task: Task, rows: list[tuple]) -> tuple[np.ndarray, ...]:
    """Rows as a Record gets them -> (image1, image2, u, state1, state2); the states as
    arrays where every row has them, else none."""
    image1, actions, image2, s1, s2 = zip(*rows, strict=True)
    u = np.stack([task.action_to_array(a) for a in actions])
    out = (np.stack(image1), np.stack(image2), u)
    if any(s is None for s in (*s1, *s2)):
        return out
    return (*out, *(np.stack([task.state_to_array(s) for s in x]) for x in (s1, s2)))
