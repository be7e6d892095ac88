"""What a recording of N tuples shows of a task, by episode length: the share of recordings that
never show some view (a model cannot know a view it never saw), and the states shown with a
move, over many seeds, in seconds.

Walks the task's rules as `lsr data generate` walks its world: the same episodes (its
`plan_episodes`: action flags and balanced starts), a random legal move per action tuple. No
physics or rendering: the walks' moves are drawn from their own generator, so a seed here is
not that seed's dataset, but the shares are those of the generator's episodes. Tasks whose
states cannot be enumerated (rope-box) have no balanced starts and are not measured.

    .venv/bin/python benchmarks/recording_coverage.py --task tshirt_folding --pairs 150 300 600 \
        --lengths 10 5 4 2 [--seeds 300]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.sim.datagen import GenerateConfig, episode_length, plan_episodes
from services.sim.worlds import world_class
from shared.tasks import get_task
from shared.tasks.base import Task


def walk(task: Task, pairs: int, length: int, seed: int) -> tuple[set, set]:
    """(views shown, states shown with a move) of one recording."""
    cfg = GenerateConfig(task=task.name, pairs=pairs, seed=seed)
    states, rng = task.all_states(), np.random.default_rng([seed, 2])
    views, moved = set(), set()
    for _, flags, first in plan_episodes(task, cfg, length):
        state = states[first]
        views.add(task.view(state))
        for is_action in flags:
            if is_action:
                legal = task.legal_actions(state)
                after = task.apply(state, legal[int(rng.integers(len(legal)))])
                moved |= {state, after}
                state = after
                views.add(task.view(state))
    return views, moved


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="tshirt_folding")
    parser.add_argument("--pairs", type=int, nargs="+", default=[150, 300, 600])
    parser.add_argument(
        "--lengths", type=int, nargs="+", help="default: the world's, the default for the size, 2"
    )
    parser.add_argument("--seeds", type=int, default=300)
    args = parser.parse_args()
    task = get_task(args.task)
    if task.all_states() is None:
        sys.exit(f"{args.task}: its states cannot be enumerated (no balanced starts)")
    views = {task.view(s) for s in task.all_states()}
    longest = world_class(args.task).episode_length
    print(f"{args.task}: {len(task.all_states())} states, {len(views)} views; {args.seeds} seeds")
    print("| tuples | episode length | recordings missing a view | states with a move (min) |")
    print("| --- | --- | --- | --- |")
    for pairs in args.pairs:
        default = episode_length(task, pairs)
        for length in args.lengths or sorted({longest, default, 2}, reverse=True):
            runs = [walk(task, pairs, length, seed) for seed in range(args.seeds)]
            missing = 100 * np.mean([len(shown) < len(views) for shown, _ in runs])
            moved = [len(m) for _, m in runs]
            marks = [m for m, n in (("the world's", longest), ("default", default)) if length == n]
            mark = f" ({', '.join(marks)})" if marks else ""
            print(
                f"| {pairs} | {length}{mark} | {missing:.1f}% "
                f"| {np.mean(moved):.1f} ({min(moved)}) |"
            )


if __name__ == "__main__":
    main()
