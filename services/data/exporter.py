"""`lsr data export`: dataset folders -> the import format (PNG images, task.json, pairs.jsonl).

A user can look at, edit and re-import what this writes; export -> import gives back the same
images, actions, episodes and splits (PNG is lossless). States are not written: the import
format has none, so a built-in task's export is that task's data without its labels.
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from tqdm import tqdm

from services.data.importer import TASK_FILE
from services.data.pairs import DataImportError
from shared import dataset as ds
from shared.images import encode_png
from shared.tasks.declared import DataTask, TaskDeclaration
from shared.workcell import Workcell


def _split_of(directory: Path, manifest: dict[str, Any]) -> str:
    """The manifest's split (imported data), else the folder's name when it is train or test."""
    split = manifest.get("split") or directory.name
    return split if split in ("train", "test") else "train"


def _episode_names(manifest: dict[str, Any], split: str):
    """A function (row index, shard's episode array or None) -> the row's episode name or None.

    Imported data records its episodes; generated data walks `episode_length` tuples from a
    reset, which is an episode too."""
    names = manifest.get("episodes")
    length = (manifest.get("config") or {}).get("episode_length")

    def name(index: int, episode: int | None) -> str | None:
        if names is not None and episode is not None:
            return names[episode]
        if length:
            return f"{split}-{index // length:05d}"
        return None

    return name


def export_dataset(
    sources: list[Path], out: Path, overwrite: bool = False, progress: bool = True
) -> dict[str, Any]:
    started = time.perf_counter()
    out = Path(out)
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise FileExistsError(f"{out} exists and is not empty; pass --overwrite to replace it")
    manifests = [ds.read_manifest(s) for s in sources]
    specs = [ds.manifest_spec(m) for m in manifests]
    first, size = specs[0], manifests[0]["image_size"]
    for source, spec, manifest in zip(sources, specs, manifests, strict=True):
        if spec.action != first.action or spec.task != first.task:
            raise DataImportError(f"{source}: another task or action than {sources[0]}")
        if manifest["image_size"] != size:
            raise DataImportError(f"{source}: {manifest['image_size']} px, {sources[0]} has {size}")
    splits = [_split_of(s, m) for s, m in zip(sources, manifests, strict=True)]
    if len(set(splits)) != len(splits):
        raise DataImportError(f"two datasets of one split ({splits}); export them one at a time")
    # the exported images are in the table frame already: at the declared size, an import
    # takes them as they are, and the markers stay for the frames a camera adds later
    markers = Workcell.from_json(manifests[0].get("markers"))
    declaration = TaskDeclaration.of_spec(first, size, manifests[0].get("settings"), markers)
    task = DataTask(replace(first, state=None))
    partial = out.with_name(f".{out.name}.partial")
    shutil.rmtree(partial, ignore_errors=True)
    counts: dict[str, int] = {}
    try:
        partial.mkdir(parents=True)
        total = sum(m["counts"]["tuples"] for m in manifests)
        bar = tqdm(total=total, unit="pair", desc="export", disable=not progress)
        with (partial / "pairs.jsonl").open("w") as pairs:
            for source, manifest, split in zip(sources, manifests, splits, strict=True):
                folder = partial / "images" / split
                folder.mkdir(parents=True)
                episode_name = _episode_names(manifest, split)
                index = 0
                for arrays in ds.iter_shards(source):
                    episodes = arrays.get("episode")
                    for i in range(len(arrays["a"])):
                        row: dict[str, Any] = {}
                        for key in ("image1", "image2"):
                            relative = f"images/{split}/{index:06d}-{key[-1]}.png"
                            (partial / relative).write_bytes(encode_png(arrays[key][i]))
                            row[key] = relative
                        action = task.array_to_action(arrays["u"][i])
                        row["action"] = None if action is None else task.action_to_json(action)
                        episode = episode_name(index, None if episodes is None else episodes[i])
                        if episode is not None:
                            row["episode"] = episode
                        row["split"] = split
                        pairs.write(json.dumps(row) + "\n")
                        index += 1
                        bar.update(1)
                counts[split] = index
        bar.close()
        text = json.dumps(declaration.to_json(), indent=2) + "\n"
        (partial / TASK_FILE).write_text(text)
        ds.publish(partial, out)
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    return {
        "task": first.task,
        "out": str(out),
        "splits": counts,
        "states_dropped": any(s.state is not None for s in specs),
        "seconds": round(time.perf_counter() - started, 2),
    }
