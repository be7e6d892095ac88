"""Judge a cloth model's plans in the simulator: the built-in one, or one trained on the cloth
data imported as a task defined by its data (which never saw a state, a rule or the sim).

    python benchmarks/data_only_judge.py --model runs/data_only_cloth/model --pairs 200
    python benchmarks/data_only_judge.py --model models/cloth_folding --pairs 200

For seeded random start/goal pairs of distinct cloth states (the same pairs for every model):
render both, plan from the start image to the goal image, and
- open loop: execute every action of the plan the APN is surest of in MuJoCo; the plan is valid
  when the simulator's read-back state is the goal (and the task's rules take the same actions
  from start to goal, reported apart);
- closed loop: `lsr eval system`'s episode (re-plan after every action, up to 20).
A data-only model's actions are its declared fields; they are the cloth task's arrays (the
export keeps the action's names, ranges and pixel frame), checked before anything runs.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from services.planner.action_plans import ActionPlanner
from services.sim.closed_loop import evaluate_system
from services.sim.worlds import make_world
from shared.plans import most_confident
from shared.tasks import get_task
from shared.tasks.base import IllegalActionError, WorldError


def cloth_planner(model: Path) -> ActionPlanner:
    """The model's planner speaking cloth actions (the same arrays, the cloth task's codecs)."""
    planner = ActionPlanner.from_model_dir(model)
    cloth = get_task("cloth_folding")
    if planner.task.spec.action.to_json() != cloth.spec.action.to_json():
        raise SystemExit(f"{model}: its actions are not the cloth task's arrays")
    return ActionPlanner(cloth, planner.planner, planner.apn)


def open_loop(planner: ActionPlanner, pairs: int, seed: int) -> dict:
    task = planner.task
    # The pairs are drawn first, from their own generator, so that every model gets the same
    # pairs whatever its plans consumed of the noise generator.
    draw = np.random.default_rng(seed)
    chosen = []
    for _ in range(pairs):
        start, goal = task.sample_state(draw), task.sample_state(draw)
        while goal == start:
            goal = task.sample_state(draw)
        chosen.append((start, goal))
    rng = np.random.default_rng([seed, 1])
    valid = by_rules = with_plan = illegal = physics = actions = 0
    with make_world(task.name, planner.image_size) as world:
        for start, goal in tqdm(chosen, desc="open loop", unit="pair"):
            world.reset(goal, rng)
            goal_image = world.render()
            world.reset(start, rng)
            plans = planner.plan(world.render(), goal_image, max_plans=8)
            if not plans:
                continue
            with_plan += 1
            plan = most_confident(plans)
            state = start
            try:
                for action in plan.actions:
                    state = task.apply(state, action)
                by_rules += state == goal
            except IllegalActionError:
                pass
            try:
                for action in plan.actions:
                    world.execute(action, rng)
                    actions += 1
                valid += world.read_state() == goal
            except IllegalActionError:
                illegal += 1
            except WorldError:
                physics += 1
    return {
        "pairs": pairs,
        "with_a_plan": 100.0 * with_plan / pairs,
        "valid_by_simulator": 100.0 * valid / pairs,
        "valid_by_rules": 100.0 * by_rules / pairs,
        "illegal_in_sim": illegal,
        "physics_failures": physics,
        "actions_executed": actions,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--model", required=True, type=Path)
    parser.add_argument("--pairs", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--closed-loop", action="store_true", help="also lsr eval system's run")
    args = parser.parse_args()
    torch.set_num_threads(1)
    planner = cloth_planner(args.model)
    started = time.perf_counter()
    result = {"model": str(args.model), "open_loop": open_loop(planner, args.pairs, args.seed)}
    if args.closed_loop:
        with make_world("cloth_folding", planner.image_size) as world:
            result["closed_loop"] = evaluate_system(
                planner, world, planner.task, args.pairs, seed=args.seed
            )
    result["seconds"] = round(time.perf_counter() - started, 1)
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
