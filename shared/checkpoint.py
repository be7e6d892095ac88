"""Model folders: a JSON config with a format and version beside safetensors weights."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


class CheckpointError(ValueError):
    """A model folder that is missing or malformed; the message names the file."""


def read_versioned_json(
    path: Path, fmt: str, version: int, kind: str, error: type[ValueError] = CheckpointError
) -> dict[str, Any]:
    """A JSON file that says which format and version it is (configs, dataset manifests)."""
    if not path.is_file():
        raise error(f"{path.parent}: no {path.name}, not {kind} folder")
    try:
        document = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise error(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(document, dict):
        raise error(f"{path}: not a {fmt} v{version} document")
    if document.get("format") != fmt:
        raise error(f"{path}: format {document.get('format')!r}, expected {fmt!r}")
    if document.get("version") != version:
        raise error(f"{path}: version {document.get('version')!r}, expected {version}")
    return document


def read_config(directory: Path | str, fmt: str, version: int, kind: str) -> dict[str, Any]:
    """config.json of a `kind` folder, checked to be of format `fmt` and `version`."""
    return read_versioned_json(Path(directory) / "config.json", fmt, version, kind)


def weights_file(directory: Path | str, name: str) -> Path:
    path = Path(directory) / name
    if not path.is_file():
        raise CheckpointError(f"{directory}: no {name}")
    return path
