"""Import what a robot recorded: camera frames and the actions between them, no simulator.

    python examples/import_recorded.py --recording rec --out data/towel
    lsr train vae --data data/towel/train --out runs/towel/vae      # then as any dataset

The recording is a folder of frames and a `log.jsonl`, one line a frame in the order seen:
`{"frame": "cam/0001.png", "action": {...} or null, "episode": 3}`, where `action` is what the
robot did after that frame (null: it only looked again). Two consecutive frames of an episode
make one tuple. This writes the import format beside them (`task.json` from TASK below, edit it
for your robot's actions; `pairs.jsonl`) and imports it: `OUT/train`, `OUT/test` (a seeded
share of the episodes), `OUT/task.json`. Every fault is refused with its file and line.
"""

from __future__ import annotations

import argparse
import json
from itertools import pairwise
from pathlib import Path

from services.data.importer import ImportConfig, import_dataset

TASK = {  # what the robot's actions are: a pick pixel in a 256 x 256 frame and a grip
    "name": "towel",
    "image_size": 64,
    "frame": 256,
    "action": [
        {"name": "pick.row", "range": [0, 255], "pixel": "row"},
        {"name": "pick.col", "range": [0, 255], "pixel": "col"},
        {"name": "grip", "categories": ["soft", "firm"]},
    ],
    "settings": {"w_eps": 0.8, "min_samples": 6},
}


def pairs(log: Path) -> list[dict]:
    """Tuples of consecutive frames within each episode of the log."""
    lines = [json.loads(line) for line in log.read_text().splitlines() if line.strip()]
    return [
        {"image1": a["frame"], "image2": b["frame"], "action": a["action"], "episode": a["episode"]}
        for a, b in pairwise(lines)
        if a["episode"] == b["episode"]
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--recording", type=Path, required=True, help="frames and log.jsonl")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()

    rows = pairs(args.recording / "log.jsonl")
    (args.recording / "task.json").write_text(json.dumps(TASK, indent=2) + "\n")
    (args.recording / "pairs.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    report = import_dataset(ImportConfig(source=args.recording, out=args.out), progress=False)
    print(json.dumps({k: report[k] for k in ("task", "rows", "action_pairs", "splits")}))


if __name__ == "__main__":
    main()
