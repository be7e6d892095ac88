"""Model folders: a JSON config with a format and version beside safetensors weights.

Writers replace files atomically and seal the folder with a manifest of their sha256 digests,
which services verify before they load it."""

from __future__ import annotations

import hashlib
import json
import os
import sys
from collections.abc import Callable, Sequence
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


MANIFEST = "MANIFEST.json"
MANIFEST_FORMAT = "lsr-manifest"


def replace_atomically(path: Path, write: Callable[[Path], object]) -> None:
    """Write `path` through a temporary file beside it, then rename: a killed run leaves the old
    file or the new one, never half of one. `write` writes the given temporary path."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        write(tmp)
        with tmp.open("rb") as written:
            os.fsync(written.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def sha256_of(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as file:
        while chunk := file.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()


def seal(directory: Path | str, names: Sequence[str]) -> None:
    """Record the sha256 of the files a writer just wrote, in MANIFEST.json, written last:
    a folder whose files do not match it was changed or half-written since."""
    directory = Path(directory)
    files = {name: sha256_of(directory / name) for name in sorted(names)}
    document = {"format": MANIFEST_FORMAT, "version": 1, "files": files}
    text = json.dumps(document, indent=2) + "\n"
    replace_atomically(directory / MANIFEST, lambda tmp: tmp.write_text(text))


def verify(directory: Path | str) -> bool:
    """Check a folder against its MANIFEST.json; False when it has none (unsealed).

    CheckpointError names the first file that is missing or differs.
    """
    directory = Path(directory)
    if not (directory / MANIFEST).is_file():
        return False
    document = read_versioned_json(directory / MANIFEST, MANIFEST_FORMAT, 1, "a sealed model")
    files = document.get("files")
    if not isinstance(files, dict) or not files:
        raise CheckpointError(f"{directory / MANIFEST}: lists no files")
    for name, expected in sorted(files.items()):
        path = directory / name
        if Path(name).name != name or not path.is_file():
            raise CheckpointError(f"{path}: listed in {MANIFEST} but missing")
        if sha256_of(path) != expected:
            raise CheckpointError(
                f"{path}: sha256 differs from {MANIFEST} (changed or half-written); "
                "refusing to load it"
            )
    return True


def main(argv: list[str]) -> int:
    """python -m shared.checkpoint seal DIR FILE... | verify DIR..."""
    if len(argv) >= 3 and argv[0] == "seal":
        seal(argv[1], argv[2:])
        print(f"sealed {argv[1]}: {', '.join(argv[2:])}")
        return 0
    if len(argv) >= 2 and argv[0] == "verify":
        for directory in argv[1:]:
            print(f"{directory}: {'verified' if verify(directory) else 'unsealed (no manifest)'}")
        return 0
    print("usage: python -m shared.checkpoint seal DIR FILE... | verify DIR...", file=sys.stderr)
    return 2


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
