from pathlib import Path

import numpy as np
import pytest

from services.planner.action_plans import ActionPlanner
from services.sim.closed_loop import evaluate_system, optimal_moves, run_episode
from shared.plans import VisualActionPlan
from shared.tasks.box_stacking import Cell, Move

SHIPPED = Path(__file__).resolve().parents[3] / "models" / "box_stacking"


class OraclePlanner:
    """Plans with the true state graph: tests the loop, not the models."""

    def __init__(self, world, goal):
        self.world, self.goal = world, goal

    def plan(self, start, goal, max_plans=8):
        task, state = self.world.task, self.world.read_state()
        if state == self.goal:
            return [VisualActionPlan([0], [start], [], [])]
        best = min(task.neighbours(state), key=lambda m: optimal_moves(task, m[1], self.goal))
        return [VisualActionPlan([0, 1], [start, goal], [best[0]], [1.0])]


class FixedPlanner:
    def __init__(self, plans):
        self.plans = plans

    def plan(self, start, goal, max_plans=8):
        return self.plans


def state(world, text):
    return world.task.parse_state({"stacks": text})


def test_optimal_moves(world):
    a = state(world, [["red", "green"], ["blue"], ["yellow"]])
    b = state(world, [["red"], ["green", "blue"], ["yellow"]])
    assert optimal_moves(world.task, a, a) == 0
    # blue out of the way, green over, blue back on top
    assert optimal_moves(world.task, a, b) == optimal_moves(world.task, b, a) == 3
    c = state(world, [["red"], ["blue"], ["yellow", "green"]])
    assert optimal_moves(world.task, a, c) == 1


def test_loop_reaches_the_goal_with_an_oracle(world):
    start = state(world, [["red", "green", "blue"], ["yellow"], []])
    goal = state(world, [[], ["yellow", "blue"], ["green", "red"]])
    episode = run_episode(OraclePlanner(world, goal), world, start, goal, np.random.default_rng(0))
    assert episode.success and episode.reason == "goal"
    assert len(episode.actions) == optimal_moves(world.task, start, goal)
    assert len(episode.images) == len(episode.actions)


def test_unreachable_and_illegal_stop_the_loop(world):
    start = state(world, [["red", "green"], ["blue"], ["yellow"]])
    goal = state(world, [["red"], ["green", "blue"], ["yellow"]])
    rng = np.random.default_rng(1)
    assert run_episode(FixedPlanner([]), world, start, goal, rng).reason == "unreachable"
    illegal = VisualActionPlan([0, 1], [], [Move(Cell(0, 0), Cell(0, 1))], [1.0])
    episode = run_episode(FixedPlanner([illegal]), world, start, goal, rng)
    assert episode.reason == "illegal_action" and episode.illegal_actions == 1
    assert episode.final_state == start and not episode.success


@pytest.mark.skipif(not (SHIPPED / "apn").is_dir(), reason="shipped model not present")
def test_shipped_model_reaches_easy_goals(world):
    import torch

    torch.set_num_threads(1)
    planner = ActionPlanner.from_model_dir(SHIPPED)
    result = evaluate_system(planner, world, world.task, pairs=5, seed=3, progress=False)
    assert result["success"] == 100.0 and result["legal_actions"] == 100.0
