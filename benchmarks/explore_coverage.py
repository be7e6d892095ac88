"""What a recording and its explored experience show of a task, judged by its rules: states seen,
states with a move, those also with 3 images or more, and the largest group of states joined by
moves. A roadmap can only plan between states in one such group, so for random start and goal
states Table I is at most about (largest group / all states)^2.

Reads the tuples' true states (simulated data); no model, in seconds.

    .venv/bin/python benchmarks/explore_coverage.py RUN/train RUN/explored_l1/experience/explore
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from shared.dataset import iter_shards, read_manifest
from shared.graphs import node_components
from shared.tasks import get_task


def coverage(folders: list[Path]) -> dict[str, float | int | None]:
    """The figures above for the tuples of `folders` (one task)."""
    tasks = {read_manifest(f)["task"] for f in folders}
    if len(tasks) != 1:
        raise SystemExit(f"the folders hold tuples of several tasks: {sorted(tasks)}")
    task = get_task(tasks.pop())
    firsts, seconds, moves = [], [], []
    for folder in folders:
        for shard in iter_shards(folder, verify=False):
            firsts.append(shard["state1"].reshape(len(shard["a"]), -1))
            seconds.append(shard["state2"].reshape(len(shard["a"]), -1))
            moves.append(shard["a"].astype(bool))
    tuples = len(np.concatenate(moves))
    states, ids, images = np.unique(
        np.concatenate(firsts + seconds), axis=0, return_inverse=True, return_counts=True
    )
    pairs = ids.reshape(2, tuples).T  # (first, second) state of each tuple
    edges = pairs[np.concatenate(moves)]
    moved = np.unique(edges)
    group = node_components(len(states), edges)
    largest = int(np.bincount(group[moved]).max()) if len(moved) else 0
    every = task.all_states()
    return {
        "states": len(every) if every is not None else None,
        "seen": len(states),
        "with_a_move": len(moved),
        "with_a_move_and_3_images": int((images[moved] >= 3).sum()),
        "largest_joined_group": largest,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folders", type=Path, nargs="+", help="datasets or experience folders")
    found = coverage(parser.parse_args().folders)
    print(", ".join(f"{k.replace('_', ' ')} {v}" for k, v in found.items()))


if __name__ == "__main__":
    main()
