"""Model folders: a JSON config with a format and version beside safetensors weights."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any


class CheckpointError(ValueError):
    """A model folder that is missing or malformed; the message names the file."""


def read_config(directory: Path | str, fmt: str, version: int, kind: str) -> dict[str, Any]:
    """config.json of a `kind` folder, checked to be of format `fmt` and `version`."""
    path = Path(directory) / "config.json"
    if not path.is_file():
        raise CheckpointError(f"{directory}: no config.json, not {kind} folder")
    try:
        config = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise CheckpointError(f"{path}: not valid JSON ({exc})") from None
    if (
        not isinstance(config, dict)
        or config.get("format") != fmt
        or config.get("version") != version
    ):
        raise CheckpointError(f"{path}: not a {fmt} v{version} config")
    return config


def weights_file(directory: Path | str, name: str) -> Path:
    path = Path(directory) / name
    if not path.is_file():
        raise CheckpointError(f"{directory}: no {name}")
    return path
