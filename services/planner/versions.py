"""Roadmap versions: a model's roadmap grows (`lsr roadmap grow`) without losing the one it had.

The built roadmap stays in `<model>/roadmap/` and is version "v1". Each growth writes a complete,
sealed folder `<model>/roadmap/versions/vK/` and only then points `<model>/roadmap/CURRENT` at it
(one atomic rename), so a reader finds the old version or the new one, never half of one, and
every older version stays where it was. Whatever takes a model folder asks `roadmap_dir` for the
folder it should read.
"""

from __future__ import annotations

import fcntl
import re
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from shared.checkpoint import replace_atomically

BASE = "roadmap"
VERSIONS = "versions"
CURRENT = "CURRENT"
FIRST = "v1"
LOCK = ".grow.lock"
_NAME = re.compile(r"v([1-9][0-9]*)")


class VersionError(ValueError):
    """A CURRENT pointer that names no version folder, or a version name that is not vK."""


def current_version(model_dir: Path | str) -> str:
    """The version the model plans with: CURRENT's name, or v1 where it never grew."""
    pointer = Path(model_dir) / BASE / CURRENT
    if not pointer.is_file():
        return FIRST
    name = pointer.read_text().strip()
    if not _NAME.fullmatch(name):
        raise VersionError(f"{pointer}: {name!r} is not a version name (v1, v2, ...)")
    return name


def version_dir(model_dir: Path | str, name: str) -> Path:
    if not _NAME.fullmatch(name):
        raise VersionError(f"{name!r} is not a version name (v1, v2, ...)")
    base = Path(model_dir) / BASE
    folder = base if name == FIRST else base / VERSIONS / name
    if not folder.is_dir():
        raise VersionError(f"{folder}: roadmap version {name} is missing")
    return folder


def roadmap_dir(model_dir: Path | str) -> Path:
    """The folder of the model's current roadmap version."""
    return version_dir(model_dir, current_version(model_dir))


def versions(model_dir: Path | str) -> list[str]:
    """Every version the model keeps, oldest first."""
    found = [FIRST] if (Path(model_dir) / BASE).is_dir() else []
    folder = Path(model_dir) / BASE / VERSIONS
    if folder.is_dir():
        names = [p.name for p in folder.iterdir() if p.is_dir() and _NAME.fullmatch(p.name)]
        found += sorted(names, key=lambda n: int(n[1:]))
    return found


def next_version(model_dir: Path | str) -> str:
    return f"v{max(int(n[1:]) for n in versions(model_dir) or [FIRST]) + 1}"


def staging_dir(model_dir: Path | str, name: str) -> Path:
    """An empty folder beside the versions where a new one is written before it is published."""
    partial = Path(model_dir) / BASE / VERSIONS / f".{name}.partial"
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    return partial


def publish(model_dir: Path | str, name: str, partial: Path) -> Path:
    """Move a finished version into place, then make it current."""
    folder = Path(model_dir) / BASE / VERSIONS / name
    if folder.exists():
        raise VersionError(f"{folder}: version {name} exists already")
    partial.rename(folder)
    make_current(model_dir, name)
    return folder


@contextmanager
def growing(model_dir: Path | str) -> Iterator[None]:
    """Hold the model's growth lock: a second growth waits until the first has published."""
    base = Path(model_dir) / BASE
    if not base.is_dir():
        raise VersionError(f"{base}: no roadmap folder")
    with open(base / LOCK, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def make_current(model_dir: Path | str, name: str) -> None:
    """Point the model at a version it keeps (a roll-back is the same call)."""
    version_dir(model_dir, name)  # exists
    pointer = Path(model_dir) / BASE / CURRENT
    replace_atomically(pointer, lambda tmp: tmp.write_text(name + "\n"))


def prune(model_dir: Path | str, keep: int) -> list[str]:
    """Delete grown versions beyond the `keep` newest, never v1, the current one or the
    highest-numbered one (so that no name is ever given to two versions: planners and viewers
    tell versions apart by name); the names deleted. Under the growth lock, and each moved
    aside before it is deleted, so no reader finds half of one (running planners hold their
    version in memory)."""
    if keep < 0:
        raise ValueError(f"keep must be >= 0, got {keep}")
    with growing(model_dir):
        current, every = current_version(model_dir), versions(model_dir)
        grown = [n for n in every if n not in (FIRST, current, every[-1])]
        doomed = grown[: max(0, len(grown) - max(0, keep - 1))]
        for name in doomed:
            folder = version_dir(model_dir, name)
            aside = folder.with_name(f".{name}.deleting")
            folder.rename(aside)
            shutil.rmtree(aside)
    return doomed
