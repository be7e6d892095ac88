"""What every `lsr` command group shares: JSON arguments, robot ids, settings, torch threads."""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path
from typing import Any


def json_arg(text: str) -> Any:
    """JSON given inline, or the path of a JSON file."""
    source = Path(text).read_text() if not text.lstrip().startswith(("{", "[")) else text
    try:
        return json.loads(source)
    except json.JSONDecodeError as exc:
        raise ValueError(f"not valid JSON: {exc}") from None


def robot_id_arg(text: str) -> str:
    from shared.bus import ROBOT_ID_PATTERN

    if not re.fullmatch(ROBOT_ID_PATTERN, text):
        raise argparse.ArgumentTypeError(
            f"{text!r} is not one zenoh key chunk: 1 to 128 characters, none of / * $ ? #, "
            "no control characters, not starting with @"
        )
    return text


def env_settings(**fields: Any):
    """Environment settings (LSR_*) with the flags that were given on top."""
    from shared.settings import Settings

    given = {k: v for k, v in fields.items() if v is not None}
    return Settings(**given)


def single_thread_torch() -> None:
    """Plans run batches of a few images: one thread beats two that spin-wait on each other."""
    import torch

    torch.set_num_threads(1)


def dataset_setting(data_dir: Path, key: str) -> Any:
    """A training setting that an imported dataset's task.json declared (`settings`), or None."""
    from shared.dataset import read_manifest

    return (read_manifest(data_dir).get("settings") or {}).get(key)
