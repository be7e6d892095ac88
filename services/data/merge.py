"""`lsr data merge`: datasets of one task joined into one, so that a model can be trained again on
what a cell recorded and what its arm did since (`lsr explore`'s or a robot's experience).

The first dataset gives the manifest (its look, markers and settings); each source is listed in
`merged_from` with its counts. Episodes stay each dataset's own: their names are prefixed by the
source's position (and dropped where a source names none).
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

from shared import dataset as ds


def _check(sources: list[Path], manifests: list[dict[str, Any]]) -> None:
    if len(sources) < 2:
        raise ds.DatasetError("merge needs two or more datasets (--data, repeated)")
    if len({s.resolve() for s in sources}) != len(sources):
        raise ds.DatasetError(f"a dataset given twice: {[str(s) for s in sources]}")
    first, spec = manifests[0], ds.manifest_spec(manifests[0])
    for source, manifest in zip(sources[1:], manifests[1:], strict=True):
        if ds.manifest_spec(manifest) != spec:
            raise ds.DatasetError(
                f"{source}: task {manifest['task']!r} with another spec than {sources[0]}'s "
                f"{first['task']!r}; only one task's datasets merge"
            )
        if manifest["image_size"] != first["image_size"]:
            raise ds.DatasetError(
                f"{source}: {manifest['image_size']} px, {sources[0]} has {first['image_size']}"
            )


def merge_datasets(sources: list[Path], out: Path, overwrite: bool = False) -> dict[str, Any]:
    """Write `out`: the tuples of every source, in order; what was merged."""
    started = time.perf_counter()
    sources, out = [Path(s) for s in sources], Path(out)
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise FileExistsError(f"{out} exists and is not empty; pass --overwrite to replace it")
    if out.resolve() in {s.resolve() for s in sources}:
        raise ds.DatasetError(f"{out}: is one of the datasets merged; write elsewhere")
    manifests = [ds.read_manifest(s) for s in sources]
    _check(sources, manifests)
    spec = ds.manifest_spec(manifests[0])
    named = all(m.get("episodes") is not None for m in manifests)
    partial = out.with_name(f".{out.name}.partial")
    shutil.rmtree(partial, ignore_errors=True)
    shards: list[dict[str, Any]] = []
    episodes: list[str] = []
    merged_from = []
    moved = 0
    try:
        partial.mkdir(parents=True)
        for k, (source, manifest) in enumerate(zip(sources, manifests, strict=True)):
            offset = len(episodes)
            if named:
                episodes += [f"{k}/{name}" for name in manifest["episodes"]]
            for arrays in ds.iter_shards(source):  # hashes checked as read
                if named:
                    arrays["episode"] = (arrays["episode"] + offset).astype(np.int32)
                else:
                    arrays.pop("episode", None)
                name = ds.shard_name(len(shards))
                digest = ds.write_shard(partial / name, arrays, spec)
                shards.append({"file": name, "count": len(arrays["a"]), "sha256": digest})
                moved += int(arrays["a"].sum())
            merged_from.append(
                {"path": str(source), "counts": manifest["counts"], "seed": manifest.get("seed")}
                | ({"experience": manifest["experience"]} if "experience" in manifest else {})
            )
        total = sum(s["count"] for s in shards)
        manifest = {k: v for k, v in manifests[0].items() if k not in ("experience", "episodes")}
        manifest |= {
            "shards": shards,
            "counts": {
                "tuples": total,
                "action_pairs": moved,
                "no_action_pairs": total - moved,
            },
            "merged_from": merged_from,
            "spec": spec.to_json(),
        }
        if named:
            manifest["episodes"] = episodes
        ds.write_manifest(partial, manifest)
        ds.publish(partial, out)
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    return {
        "task": spec.task,
        "out": str(out),
        "tuples": total,
        "action_pairs": moved,
        "sources": len(sources),
        "seconds": round(time.perf_counter() - started, 2),
    }
