"""On-disk dataset of (image 1, image 2, a, u, state 1, state 2) tuples, without pickle.

Layout of a dataset folder:
  manifest.json        format, version, task, spec, image size, seed, counts, shards with sha256
  shard-00000.npz ...  uncompressed-header zip of .npy arrays, one entry per field:
    image1, image2  uint8  (n, H, W, 3)
    a               uint8  (n,)     1 = action pair, 0 = no-action pair
    u               spec.action.dtype  (n, *spec.action.shape)  -1 everywhere when a = 0
    state1, state2  spec.state.dtype   (n, *spec.state.shape)
    episode         int32  (n,)     optional: index into the manifest's `episodes` (imported data)
The manifest's `spec` (a `TaskSpec`) declares the arrays, so readers never look shapes up in
the task registry; manifests written before it existed get the registered task's spec.
Zip entries carry a fixed timestamp, so the same seed gives the same bytes.
"""

from __future__ import annotations

import hashlib
import io
import json
import shutil
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from shared.checkpoint import read_versioned_json
from shared.tasks.spec import SpecError, TaskSpec

FORMAT = "lsr-dataset"
VERSION = 1
FIELDS = ("image1", "image2", "a", "u", "state1", "state2")
OPTIONAL = ("episode",)  # written when present; old readers ignore it
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)


class DatasetError(ValueError):
    """A dataset folder that is missing, malformed or corrupted."""


@dataclass
class Dataset:
    manifest: dict[str, Any]
    image1: np.ndarray
    image2: np.ndarray
    a: np.ndarray
    u: np.ndarray
    state1: np.ndarray
    state2: np.ndarray
    episode: np.ndarray | None = None  # index into manifest["episodes"], where recorded

    def __len__(self) -> int:
        return len(self.a)

    @property
    def task(self) -> str:
        return self.manifest["task"]

    @property
    def image_size(self) -> int:
        return self.manifest["image_size"]

    @property
    def spec(self) -> TaskSpec:
        return manifest_spec(self.manifest)


def manifest_spec(manifest: dict[str, Any]) -> TaskSpec:
    """The dataset's declared arrays; the registered task's for manifests that predate specs,
    or that predate what a built-in task has since learned to declare (its `undo`)."""
    from shared.tasks import get_task, has_simulator

    if "spec" not in manifest:
        return get_task(manifest["task"]).spec
    try:
        spec = TaskSpec.from_json(manifest["spec"])
    except SpecError as exc:
        raise DatasetError(f"manifest.json: {exc}") from None
    if not spec.undo and has_simulator(spec.task) and get_task(spec.task).spec == spec:
        return get_task(spec.task).spec
    return spec


def validate_arrays(spec: TaskSpec, arrays: dict[str, np.ndarray]) -> None:
    """Raise DatasetError naming the field unless the arrays are what `spec` declares."""
    n = len(arrays["a"])
    try:
        for name in FIELDS:
            if len(arrays[name]) != n:
                raise SpecError(f"{name}: {len(arrays[name])} rows, 'a' has {n}")
        if "episode" in arrays and (
            arrays["episode"].shape != (n,) or arrays["episode"].dtype != np.int32
        ):
            raise SpecError(f"episode: expected int32 of shape ({n},)")
        spec.action.validate(arrays["u"], "u")
        if spec.state is not None:
            spec.state.validate(arrays["state1"], "state1")
            spec.state.validate(arrays["state2"], "state2")
    except SpecError as exc:
        raise DatasetError(str(exc)) from None


def write_shard(path: Path, arrays: dict[str, np.ndarray], spec: TaskSpec) -> str:
    """Write arrays as a deterministic .npz after checking them against `spec`; its sha256."""
    validate_arrays(spec, arrays)
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=6) as zf:
        for name in (*FIELDS, *(f for f in OPTIONAL if f in arrays)):
            entry = io.BytesIO()
            np.lib.format.write_array(entry, np.ascontiguousarray(arrays[name]), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_DATE)
            info.compress_type = zipfile.ZIP_DEFLATED
            zf.writestr(info, entry.getvalue())
    data = buffer.getvalue()
    path.write_bytes(data)
    return hashlib.sha256(data).hexdigest()


def read_shard(path: Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as npz:
        missing = [f for f in FIELDS if f not in npz.files]
        if missing:
            raise DatasetError(f"{path}: missing arrays {missing}")
        return {f: npz[f] for f in (*FIELDS, *(f for f in OPTIONAL if f in npz.files))}


def read_manifest(directory: Path | str) -> dict[str, Any]:
    path = Path(directory) / "manifest.json"
    if not path.is_file() and Path(directory).is_dir():
        inside = sorted(p.parent.name for p in Path(directory).glob("*/manifest.json"))
        if inside:  # an import's folder: OUT/train, OUT/test
            hint = ", ".join(str(Path(directory) / name) for name in inside)
            raise DatasetError(f"{path}: missing; the datasets are one level down: {hint}")
    return read_versioned_json(path, FORMAT, VERSION, "a dataset", DatasetError)


def iter_shards(directory: Path | str, verify: bool = True) -> Iterator[dict[str, np.ndarray]]:
    directory = Path(directory)
    manifest = read_manifest(directory)
    for shard in manifest["shards"]:
        path = directory / shard["file"]
        if not path.is_file():
            raise DatasetError(f"{path}: shard listed in the manifest is missing")
        if verify and hashlib.sha256(path.read_bytes()).hexdigest() != shard["sha256"]:
            raise DatasetError(f"{path}: sha256 differs from the manifest, the file is corrupted")
        arrays = read_shard(path)
        if len(arrays["a"]) != shard["count"]:
            raise DatasetError(f"{path}: {len(arrays['a'])} tuples, manifest says {shard['count']}")
        yield arrays


def load_dataset(directory: Path | str, verify: bool = True) -> Dataset:
    manifest = read_manifest(directory)
    parts: dict[str, list[np.ndarray]] = {f: [] for f in (*FIELDS, *OPTIONAL)}
    for arrays in iter_shards(directory, verify=verify):
        for f in arrays:
            parts[f].append(arrays[f])
    if not parts["a"]:
        raise DatasetError(f"{directory}: the dataset has no shards")
    columns = {f: np.concatenate(parts[f]) for f in FIELDS}
    optional = {f: np.concatenate(parts[f]) for f in OPTIONAL if len(parts[f]) == len(parts["a"])}
    return Dataset(manifest, **columns, **optional)


def write_manifest(directory: Path, manifest: dict[str, Any]) -> None:
    (directory / "manifest.json").write_text(json.dumps(manifest, indent=2, sort_keys=True) + "\n")


def publish(partial: Path, out: Path) -> None:
    """Move a finished folder built beside its destination into place, replacing what was there."""
    if out.exists():
        shutil.rmtree(out)
    partial.rename(out)


def shard_name(index: int) -> str:
    return f"shard-{index:05d}.npz"
