"""The import format's rows: `pairs.jsonl` or `pairs.csv`, read one line at a time.

A row names two images (paths relative to the dataset folder), the action between them (an
object in the declared fields, or null for a no-action pair) and optionally its episode and
split. Every error names the file and line.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

PAIRS_FILES = ("pairs.jsonl", "pairs.csv")
KEYS = ("image1", "image2", "action", "episode", "split")
SPLITS = ("train", "test")


class DataImportError(ValueError):
    """Input that cannot be imported; the message names the file (and line) at fault."""


@dataclass(frozen=True)
class Row:
    line: int
    image1: str
    image2: str
    action: Any  # the action's JSON object, or None (no-action pair)
    episode: str | None
    split: str | None


def pairs_file(source: Path) -> Path:
    found = [source / name for name in PAIRS_FILES if (source / name).is_file()]
    if not found:
        raise DataImportError(f"{source}: no pairs.jsonl or pairs.csv")
    if len(found) > 1:
        raise DataImportError(f"{source}: both pairs.jsonl and pairs.csv; keep one")
    return found[0]


def _raw_rows(path: Path) -> Iterator[tuple[int, dict[str, Any]]]:
    """(line number, the row's object) of a .jsonl or .csv file; blank lines skipped."""
    with path.open(newline="" if path.suffix == ".csv" else None, encoding="utf-8") as file:
        if path.suffix == ".jsonl":
            for number, text in enumerate(file, start=1):
                if not text.strip():
                    continue
                try:
                    obj = json.loads(text)
                except json.JSONDecodeError as exc:
                    raise DataImportError(f"{path}:{number}: not valid JSON ({exc.msg})") from None
                if not isinstance(obj, dict):
                    raise DataImportError(f"{path}:{number}: expected a JSON object")
                yield number, obj
            return
        reader = csv.DictReader(file)
        header = reader.fieldnames or []
        unknown = [k for k in header if k not in KEYS]
        if unknown or not {"image1", "image2", "action"} <= set(header):
            raise DataImportError(
                f"{path}:1: the header must name image1, image2, action "
                f"(and optionally episode, split); got {header}"
            )
        for record in reader:
            number = reader.line_num
            if None in record:
                raise DataImportError(f"{path}:{number}: more cells than the header has")
            row: dict[str, Any] = {k: v for k, v in record.items() if v not in ("", None)}
            text = row.get("action", "null")
            try:
                row["action"] = json.loads(text)
            except json.JSONDecodeError as exc:
                raise DataImportError(
                    f"{path}:{number}: action: not valid JSON ({exc.msg}); "
                    "write the object, or null or nothing for a no-action pair"
                ) from None
            yield number, row


def read_rows(path: Path) -> Iterator[Row]:
    """Rows with their keys checked (types and known names; not images nor actions)."""
    for number, obj in _raw_rows(path):
        where = f"{path}:{number}"
        unknown = [k for k in obj if k not in KEYS]
        if unknown:
            raise DataImportError(f"{where}: unknown key {unknown[0]!r}; a row has {list(KEYS)}")
        for key in ("image1", "image2"):
            value = obj.get(key)
            if not isinstance(value, str) or not value:
                raise DataImportError(f"{where}: {key}: expected an image path")
        if "action" not in obj:
            raise DataImportError(f"{where}: action: missing (null for a no-action pair)")
        episode = obj.get("episode")
        if episode is not None:
            if isinstance(episode, bool) or not isinstance(episode, str | int) or episode == "":
                raise DataImportError(f"{where}: episode: expected a string or an integer")
            episode = str(episode)
        split = obj.get("split")
        if split is not None and split not in SPLITS:
            raise DataImportError(f"{where}: split: expected one of {list(SPLITS)}, got {split!r}")
        action = obj["action"]
        if action is not None and not isinstance(action, dict):
            raise DataImportError(f"{where}: action: expected an object or null")
        yield Row(number, obj["image1"], obj["image2"], action, episode, split)


def count_lines(path: Path) -> int:
    """Lines in the file (for the progress bar's total); read in blocks, not held."""
    with path.open("rb") as file:
        return sum(block.count(b"\n") for block in iter(lambda: file.read(1 << 20), b""))
