"""Import throughput and memory: N tuples of 256 px JPEGs -> a 64 px dataset.

    python benchmarks/bench_import.py                 # 1000 and 5000 tuples
    python benchmarks/bench_import.py --tuples 5000

Each size is written as a recorded dataset (2 JPEGs a tuple, episodes of 10, a task.json with
the cloth task's pixel actions) and imported by `lsr data import` in a fresh process, whose
peak resident memory (ru_maxrss) and wall time are printed. Memory should not grow with N: the
import holds one shard (1000 tuples at 64 px: 25 MB of images) and a few bytes per row.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from PIL import Image

TASK = {
    "name": "bench_import",
    "image_size": 64,
    "frame": 256,
    "action": [
        {"name": "pick.row", "range": [0, 255], "pixel": "row"},
        {"name": "pick.col", "range": [0, 255], "pixel": "col"},
        {"name": "release.row", "range": [0, 255], "pixel": "row"},
        {"name": "release.col", "range": [0, 255], "pixel": "col"},
        {"name": "height", "categories": ["table", "top"]},
    ],
}


def write_recorded(root: Path, tuples: int, seed: int = 0) -> None:
    """Camera-like 256 px JPEGs: a smooth background, a bright patch, sensor noise."""
    rng = np.random.default_rng(seed)
    (root / "images").mkdir(parents=True)
    (root / "task.json").write_text(json.dumps(TASK))
    yy, xx = np.mgrid[0:256, 0:256]
    with (root / "pairs.jsonl").open("w") as pairs:
        for i in range(tuples):
            names = []
            for k in (1, 2):
                r, c = rng.integers(40, 216, size=2)
                base = 90 + 40 * np.sin(xx / 37.0 + i) + 30 * np.cos(yy / 23.0)
                patch = ((yy - r) ** 2 + (xx - c) ** 2 < 900) * 100
                image = base[..., None] + patch[..., None] + rng.normal(0, 6, (256, 256, 3))
                name = f"images/{i:06d}_{k}.jpg"
                Image.fromarray(np.clip(image, 0, 255).astype(np.uint8)).save(
                    root / name, quality=90
                )
                names.append(name)
            action = None
            if rng.random() < 0.65:
                p, q = rng.integers(0, 256, size=(2, 2))
                action = {
                    "pick": {"row": int(p[0]), "col": int(p[1])},
                    "release": {"row": int(q[0]), "col": int(q[1])},
                    "height": ["table", "top"][int(rng.integers(2))],
                }
            row = {"image1": names[0], "image2": names[1], "action": action, "episode": i // 10}
            pairs.write(json.dumps(row) + "\n")


# The child reports its own peak: RUSAGE_CHILDREN would be a running max over every run.
CHILD = """
import resource, sys
from services.cli import main
code = main(sys.argv[1:])
print("peak_rss_kb", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, file=sys.stderr)
raise SystemExit(code)
"""


def measure(source: Path, out: Path) -> dict:
    """Import in a fresh process: its wall time and peak RSS."""
    started = time.perf_counter()
    command = [sys.executable, "-c", CHILD, "data", "import", "--from", str(source),
               "--out", str(out)]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    seconds = time.perf_counter() - started
    if done.returncode != 0:
        raise SystemExit(done.stderr)
    peak = int(done.stderr.strip().splitlines()[-1].split()[-1])
    result = json.loads(done.stdout.strip().splitlines()[-1])
    return {
        "tuples": result["rows"],
        "images": result["images"],
        "seconds": round(seconds, 1),
        "check_seconds": result["check_seconds"],
        "peak_rss_mb": round(peak / 1024, 1),
        "progress_bar": "import:" in done.stderr,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--tuples", type=int, action="append")
    parser.add_argument(
        "--keep", type=Path, help="write the JPEGs under this folder and reuse them next time"
    )
    args = parser.parse_args()
    sizes = args.tuples or [1000, 5000]
    for tuples in sizes:
        with tempfile.TemporaryDirectory() as tmp:
            source = (args.keep or Path(tmp)) / f"recorded-{tuples}"
            started = time.perf_counter()
            if not (source / "pairs.jsonl").is_file():
                write_recorded(source, tuples)
            written = time.perf_counter() - started
            row = measure(source, Path(tmp) / "imported")
            row["write_jpegs_seconds"] = round(written, 1)
            print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
