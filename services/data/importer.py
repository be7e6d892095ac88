"""`lsr data import`: recorded image pairs -> the project's dataset folders (train/, test/).

Two passes over `pairs.jsonl` / `pairs.csv`, each streaming: the first checks every row and
every image (and decides the split) before anything is written, the second decodes, resizes
and writes shards of `shard_size` tuples into a folder beside the output, renamed into place
only when complete. Memory holds one shard and a few bytes per row (duplicate keys, episode
ids), never the images.
"""

from __future__ import annotations

import hashlib
import io
import json
import shutil
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image
from tqdm import tqdm

from services.data.pairs import DataImportError, count_lines, pairs_file, read_rows
from shared import dataset as ds
from shared.images import ImageError, decode_image
from shared.registration import Registration, to_table_frame
from shared.tasks import get_task, task_names
from shared.tasks.base import InvalidActionError
from shared.tasks.declared import DataTask, DeclarationError, TaskDeclaration
from shared.tasks.spec import NULL

TASK_FILE = "task.json"


@dataclass(frozen=True)
class ImportConfig:
    source: Path
    out: Path
    name: str | None = None  # replaces task.json's name (say, to re-import a built-in's export)
    test_fraction: float = 0.2  # of the episodes, when the rows give no split
    seed: int = 0
    shard_size: int = 1000
    overwrite: bool = False

    def __post_init__(self) -> None:
        if not 0 <= self.test_fraction < 1:
            raise ValueError(f"test fraction must be in [0, 1), got {self.test_fraction}")
        if self.shard_size < 1:
            raise ValueError("shard size must be at least 1")


@dataclass
class Checked:
    """What the checking pass found: enough to write without deciding anything again."""

    declaration: TaskDeclaration
    pairs: Path
    registration: Registration | None = None  # the declared markers'
    rows: int = 0
    action_pairs: int = 0
    images: int = 0  # distinct image files
    registered: int = 0  # of them, camera frames registered to the table frame (markers)
    resized: int = 0  # of them, without markers: not of the declared size (resized)
    cropped: int = 0  # of those, not square (centre-cropped first: the aspect is kept)
    sizes: Counter = field(default_factory=Counter)
    episodes: dict[str, int] = field(default_factory=dict)  # name -> index, first-seen order
    row_episode: list[int] = field(default_factory=list)  # per row: its episode's index
    row_split: list[str] = field(default_factory=list)  # per row: "train" | "test"
    own_episodes: bool = False  # rows gave no episode: each row is its own
    split_from: str = "seeded by episode"


def read_declaration(source: Path, name: str | None) -> TaskDeclaration:
    path = source / TASK_FILE
    if not path.is_file():
        raise DataImportError(f"{source}: no {TASK_FILE} declaring the task")
    try:
        obj = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataImportError(f"{path}: not valid JSON ({exc})") from None
    if name is not None and isinstance(obj, dict):
        obj = {**obj, "name": name}
    try:
        return TaskDeclaration.from_json(obj)
    except DeclarationError as exc:
        raise DataImportError(f"{path}: {exc}") from None


def check_name(source: Path, declaration: TaskDeclaration) -> None:
    """A built-in task's name is that task only with its actions (what `lsr data export` of
    its dataset writes, so that the round trip needs no flags); otherwise it clashes."""
    name = declaration.name
    if name in task_names() and get_task(name).spec.action != declaration.spec.action:
        raise DataImportError(
            f"{source / TASK_FILE}: name {name!r} clashes with a built-in task "
            f"({task_names()}) whose actions differ; rename it, or import with --name NEW"
        )


def _image_path(source: Path, where: str, key: str, relative: str) -> Path:
    path = (source / relative).resolve()
    if Path(relative).is_absolute() or not path.is_relative_to(source.resolve()):
        raise DataImportError(f"{where}: {key}: {relative!r} is not inside {source}")
    return path


def load_image(
    path: Path, size: int, registration: Registration | None = None
) -> tuple[np.ndarray, bool]:
    """The image as uint8 (size, size, 3), and whether it had to be cropped and resized; with
    a `registration` (the task's markers), a camera frame registered to the table frame
    (ImageError when its markers are not found)."""
    try:
        image = decode_image(path.read_bytes(), at_least=None if registration else size)
    except OSError as exc:
        raise ImageError(f"cannot be read ({exc.strerror or exc})") from None
    h, w = image.shape[:2]
    if registration is not None:
        (registered,), (why,) = to_table_frame(registration, [image])
        if why is not None:
            raise ImageError(why)
        return registered, (h, w) != (size, size)
    if (h, w) == (size, size):
        return image, False
    side = min(h, w)  # the centre square keeps the aspect: nothing stretched
    top, left = (h - side) // 2, (w - side) // 2
    square = Image.fromarray(image[top : top + side, left : left + side])
    resized = square.resize((size, size), Image.Resampling.LANCZOS, reducing_gap=None)
    return np.asarray(resized, dtype=np.uint8), True


def _checked_size(path: Path, size: int) -> tuple[int, int]:
    """The image's (width, height), after decoding all of it (a truncated file fails here;
    a JPEG is scaled in the decoder, which still reads every byte)."""
    data = path.read_bytes()
    try:
        with Image.open(io.BytesIO(data)) as img:
            original = img.size
    except Exception as exc:
        raise ImageError(f"not a readable PNG or JPEG image ({exc})") from None
    decode_image(data, at_least=size)
    return original


def check(cfg: ImportConfig, progress: bool = True) -> Checked:
    """Every row and image checked, the split decided; DataImportError at the first fault."""
    source = Path(cfg.source)
    if not source.is_dir():
        raise DataImportError(f"{source}: not a folder")
    declaration = read_declaration(source, cfg.name)
    task = DataTask(declaration.spec)
    pairs = pairs_file(source)
    size = declaration.image_size
    markers = declaration.markers
    found = Checked(declaration, pairs, None if markers is None else Registration(markers, size))
    refused: list[str] = []  # frames whose markers were not found, reported all at once
    checked_images: set[Path] = set()
    seen: dict[bytes, int] = {}  # row key -> its first line
    splits_given: list[bool] = []
    total = count_lines(pairs)
    bar = tqdm(total=total, unit="row", desc="check", disable=not progress)
    for row in read_rows(pairs):
        where = f"{pairs}:{row.line}"
        paths = []
        for key, relative in (("image1", row.image1), ("image2", row.image2)):
            path = _image_path(source, where, key, relative)
            if not path.is_file():
                raise DataImportError(f"{where}: {key}: {relative} does not exist")
            if path not in checked_images:
                try:
                    w, h = _checked_size(path, size)
                except (ImageError, OSError) as exc:
                    raise DataImportError(f"{where}: {key}: {relative}: {exc}") from None
                if found.registration is not None:
                    try:
                        load_image(path, size, found.registration)
                    except ImageError as exc:
                        refused.append(f"{where}: {key}: {relative}: {exc}")
                    found.registered += 1
                else:
                    found.resized += (w, h) != (size, size)
                    found.cropped += w != h
                found.sizes[f"{w}x{h}"] += 1
                checked_images.add(path)
            paths.append(path)
        if row.action is not None:
            try:
                task.parse_action(row.action)
            except InvalidActionError as exc:
                raise DataImportError(f"{where}: action: {exc}") from None
            found.action_pairs += 1
        key = hashlib.blake2b(
            json.dumps([str(paths[0]), str(paths[1]), row.action], sort_keys=True).encode(),
            digest_size=16,
        ).digest()
        if key in seen:
            raise DataImportError(f"{where}: duplicate of line {seen[key]} (same images, action)")
        seen[key] = row.line
        if splits_given and splits_given[0] != (row.split is not None):
            raise DataImportError(
                f"{where}: split: given on some rows and not on others; give it on all or none"
            )
        splits_given.append(row.split is not None)
        episode = row.episode if row.episode is not None else f"line-{row.line}"
        found.own_episodes |= row.episode is None
        found.row_episode.append(found.episodes.setdefault(episode, len(found.episodes)))
        found.row_split.append(row.split or "")
        found.rows += 1
        bar.update(1)
    bar.close()
    if found.rows == 0:
        raise DataImportError(f"{pairs}: no rows")
    if refused:
        raise DataImportError(
            f"{len(refused)} image(s) could not be registered to the table frame (task.json's "
            f"markers); remove their rows or retake them. First: " + "; ".join(refused[:3])
        )
    check_name(source, declaration)  # after every file: a user fixes all there is at once
    found.images = len(checked_images)
    if not splits_given[0]:
        _split_by_episode(found, cfg)
    else:
        found.split_from = "the rows' split column"
        mixed = _episodes_in_both(found)
        if mixed:
            raise DataImportError(
                f"{pairs}: episode {mixed!r} has rows in both train and test; a test pair must "
                "not share an episode with training pairs"
            )
    return found  # a split column of test rows only is held-out data for a trained model


def _episodes_in_both(found: Checked) -> str | None:
    splits: dict[int, set[str]] = {}
    for episode, split in zip(found.row_episode, found.row_split, strict=True):
        splits.setdefault(episode, set()).add(split)
    names = list(found.episodes)
    return next((names[e] for e, s in splits.items() if len(s) > 1), None)


def _split_by_episode(found: Checked, cfg: ImportConfig) -> None:
    """A seeded share of the episodes (never of the pairs) is the test split."""
    n = len(found.episodes)
    n_test = round(cfg.test_fraction * n)
    if cfg.test_fraction > 0 and n >= 2:
        n_test = min(max(n_test, 1), n - 1)
    test = set(np.random.default_rng(cfg.seed).permutation(n)[:n_test].tolist())
    found.row_split = ["test" if e in test else "train" for e in found.row_episode]


def import_dataset(cfg: ImportConfig, progress: bool = True) -> dict[str, Any]:
    """Check everything, then write `out/train` and `out/test` (each when it has rows) and
    `out/task.json`."""
    started = time.perf_counter()
    out = Path(cfg.out)
    if out.exists() and any(out.iterdir()) and not cfg.overwrite:
        raise FileExistsError(f"{out} exists and is not empty; pass --overwrite to replace it")
    found = check(cfg, progress)
    checked = time.perf_counter()
    partial = out.with_name(f".{out.name}.partial")
    shutil.rmtree(partial, ignore_errors=True)
    try:
        splits = _write(cfg, found, partial, progress)
        text = json.dumps(found.declaration.to_json(), indent=2) + "\n"
        (partial / TASK_FILE).write_text(text)
        ds.publish(partial, out)
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    return {
        "task": found.declaration.name,
        "out": str(out),
        "rows": found.rows,
        "action_pairs": found.action_pairs,
        "images": found.images,
        "image_sizes": dict(found.sizes),
        "registered": found.registered,
        "resized": found.resized,
        "cropped": found.cropped,
        "image_size": found.declaration.image_size,
        "episodes": len(found.episodes),
        "own_episodes": found.own_episodes,
        "split": found.split_from,
        "splits": splits,
        "check_seconds": round(checked - started, 2),
        "seconds": round(time.perf_counter() - started, 2),
    }


def _write(
    cfg: ImportConfig, found: Checked, partial: Path, progress: bool
) -> dict[str, dict[str, int]]:
    spec = found.declaration.spec
    task = DataTask(spec)
    size = found.declaration.image_size
    source = Path(cfg.source)
    names = list(found.episodes)
    writers = {
        split: _SplitWriter(partial / split, cfg, found, split)
        for split in ("train", "test")
        if split in found.row_split
    }
    bar = tqdm(total=found.rows, unit="pair", desc="import", disable=not progress)
    for index, row in enumerate(read_rows(found.pairs)):
        image1, _ = load_image(source / row.image1, size, found.registration)
        image2, _ = load_image(source / row.image2, size, found.registration)
        action = None if row.action is None else task.parse_action(row.action)
        writer = writers[found.row_split[index]]
        writer.add(image1, image2, task.action_to_array(action), names[found.row_episode[index]])
        bar.update(1)
    bar.close()
    if index + 1 != found.rows:
        raise DataImportError(f"{found.pairs}: changed while importing")
    return {split: writer.close() for split, writer in writers.items()}


class _SplitWriter:
    """Rows of one split into shards, then its manifest."""

    def __init__(self, directory: Path, cfg: ImportConfig, found: Checked, split: str) -> None:
        directory.mkdir(parents=True)
        self.directory, self.cfg, self.found, self.split = directory, cfg, found, split
        self.rows: list[tuple[np.ndarray, np.ndarray, np.ndarray, int]] = []
        self.shards: list[dict[str, Any]] = []
        self.episodes: dict[str, int] = {}
        self.count = self.action_pairs = 0

    def add(self, image1: np.ndarray, image2: np.ndarray, u: np.ndarray, episode: str) -> None:
        index = self.episodes.setdefault(episode, len(self.episodes))
        self.rows.append((image1, image2, u, index))
        self.count += 1
        self.action_pairs += int((u != NULL).any())
        if len(self.rows) >= self.cfg.shard_size:
            self._flush()

    def _flush(self) -> None:
        if not self.rows:
            return
        spec = self.found.declaration.spec
        u = np.stack([r[2] for r in self.rows])
        arrays = {
            "image1": np.stack([r[0] for r in self.rows]),
            "image2": np.stack([r[1] for r in self.rows]),
            "a": (u != NULL).any(axis=1).astype(np.uint8),
            "u": u,
            "state1": np.zeros((len(u), 0), np.int8),
            "state2": np.zeros((len(u), 0), np.int8),
            "episode": np.array([r[3] for r in self.rows], dtype=np.int32),
        }
        name = ds.shard_name(len(self.shards))
        sha = ds.write_shard(self.directory / name, arrays, spec)
        self.shards.append({"file": name, "count": len(u), "sha256": sha})
        self.rows = []

    def close(self) -> dict[str, int]:
        self._flush()
        declaration = self.found.declaration
        manifest = {
            "format": ds.FORMAT,
            "version": ds.VERSION,
            "task": declaration.name,
            "spec": declaration.spec.to_json(),
            "image_size": declaration.image_size,
            "seed": self.cfg.seed,
            "split": self.split,
            "counts": {
                "tuples": self.count,
                "action_pairs": self.action_pairs,
                "no_action_pairs": self.count - self.action_pairs,
            },
            "settings": dict(declaration.settings),
            # the table's markers; images were registered to the table frame with them
            "markers": None if declaration.markers is None else declaration.markers.to_json(),
            "source": {"pairs": str(self.found.pairs), "split": self.found.split_from},
            "episodes": list(self.episodes),
            "shards": self.shards,
        }
        ds.write_manifest(self.directory, manifest)
        return {
            "tuples": self.count,
            "action_pairs": self.action_pairs,
            "episodes": len(self.episodes),
        }
