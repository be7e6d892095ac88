import itertools
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from services.planner.action_plans import ActionPlanner
from services.planner.roadmap import Roadmap, RoadmapConfig
from services.sim.closed_loop import TryShortcuts, evaluate_system, optimal_moves, run_episode
from shared.plans import Match, UnknownImageError, VisualActionPlan
from shared.tasks.base import IllegalActionError, WorldError
from shared.tasks.box_stacking import Cell, Move

SHIPPED = Path(__file__).resolve().parents[3] / "models" / "box_stacking"


class OraclePlanner:
    """Plans with the true state graph: tests the loop, not the models."""

    def __init__(self, world, goal):
        self.world, self.goal = world, goal

    def plan(self, start, goal, max_plans=8, expect=None, avoid=()):
        task, state = self.world.task, self.world.read_state()
        if task.view(state) == task.view(self.goal):
            return [VisualActionPlan([0], [start], [], [], [])]
        best = min(task.neighbours(state), key=lambda m: optimal_moves(task, m[1], self.goal))
        return [VisualActionPlan([0, 1], [start, goal], [best[0]], [1.0], [1])]


class FixedPlanner:
    def __init__(self, plans):
        self.plans = plans

    def plan(self, start, goal, max_plans=8, expect=None, avoid=()):
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


def test_a_goal_with_a_hidden_sleeve_is_reached_when_the_scene_shows_its_view():
    """interface.md, "Views": success is the goal's view, whatever the sleeve under the
    folded side does; the fewest moves to it skip folding that sleeve."""
    from services.sim.tshirt_folding.world import TshirtFoldingWorld

    with TshirtFoldingWorld(image_size=32) as shirt:
        task = shirt.task
        start = task.parse_state({"folds": []})
        goal = task.parse_state({"folds": ["left_sleeve", "left_side", "bottom_half"]})
        episode = run_episode(
            OraclePlanner(shirt, goal), shirt, start, goal, np.random.default_rng(4)
        )
        assert episode.success and episode.reason == "goal"
        assert episode.final_state == ("left_side", "bottom_half") != goal
        assert len(episode.actions) == optimal_moves(task, start, goal) == 2


class WrongStepPlanner:
    """Plans on a real roadmap of four states whose action for step 0 -> 1 leads to node 3, a
    dead end joined only to node 0; the honest way round is 0 -> 2 -> 1."""

    def __init__(self, world, states):
        self.world, self.ids, self.avoided = world, {s: i for i, s in enumerate(states)}, []
        edges = [(0, 1), (0, 2), (0, 3), (1, 2)]
        self.roadmap = Roadmap(
            config=RoadmapConfig(),
            epsilon=1.0,
            mu0=0.5,
            sigma0=0.5,
            nodes=np.eye(4, dtype=np.float32),
            node_sizes=np.ones(4, np.int64),
            edges=np.array(edges, np.int64),
            edge_weights=np.ones(4, np.int64),
            point_node=np.zeros(0, np.int64),
        )
        move = {
            (i, j): m
            for e in edges
            for i, j in (e, e[::-1])
            for m, after in world.task.neighbours(states[i])
            if after == states[j]
        }
        self.actions = {**move, (0, 1): move[(0, 3)]}  # the wrong one

    def plan(self, start, goal, max_plans=8, *, expect=None, avoid=()):  # by name, as clients
        self.avoided.append(tuple(avoid))
        here = self.ids[self.world.read_state()]
        paths = self.roadmap.shortest_paths(here, 1, max_plans, avoid)
        steps = [list(itertools.pairwise(p)) for p in paths]
        return [
            VisualActionPlan(p, [], [self.actions[s] for s in st], [1.0] * len(st), [1] * len(st))
            for p, st in zip(paths, steps, strict=True)
        ]


def test_a_step_whose_action_led_elsewhere_is_avoided_for_the_rest_of_the_task(world):
    a = state(world, [["red", "green"], ["blue"], ["yellow"]])
    goal = state(world, [["red"], ["blue", "green"], ["yellow"]])
    aside = state(world, [["red"], ["blue"], ["yellow", "green"]])
    dead_end = state(world, [["red", "green", "yellow"], ["blue"], []])
    planner = WrongStepPlanner(world, [a, goal, aside, dead_end])
    episode = run_episode(planner, world, a, goal, np.random.default_rng(0))
    assert episode.success and len(episode.actions) == 4  # wrong, back, round by node 2
    assert episode.states == [a, dead_end, a, aside, goal]
    assert planner.avoided == [(), (), ((0, 1),), ((0, 1),)]


def test_unreachable_and_illegal_stop_the_loop(world):
    start = state(world, [["red", "green"], ["blue"], ["yellow"]])
    goal = state(world, [["red"], ["green", "blue"], ["yellow"]])
    rng = np.random.default_rng(1)
    assert run_episode(FixedPlanner([]), world, start, goal, rng).reason == "unreachable"
    illegal = VisualActionPlan([0, 1], [], [Move(Cell(0, 0), Cell(0, 1))], [1.0], [1])
    episode = run_episode(FixedPlanner([illegal]), world, start, goal, rng)
    assert episode.reason == "illegal_action" and episode.illegal_actions == 1
    assert episode.final_state == start and not episode.success


class ScenePlanner:
    """Knows the scene until `known` actions have been executed, then refuses its start."""

    def __init__(self, world, goal, known):
        self.oracle, self.known, self.calls = OraclePlanner(world, goal), known, 0

    def plan(self, start, goal, max_plans=8, expect=None, avoid=()):
        self.calls += 1
        if self.calls > self.known:
            match = {"start": Match(False, 4.2, 7), "goal": Match(True, 0.1, 3)}
            raise UnknownImageError("start", "the start image is unlike anything", match)
        return self.oracle.plan(start, goal, max_plans)


def test_an_unknown_observed_scene_stops_the_loop_without_acting_on_it(world):
    start = state(world, [["red", "green", "blue"], ["yellow"], []])
    goal = state(world, [[], ["yellow", "blue"], ["green", "red"]])
    planner = ScenePlanner(world, goal, known=1)
    episode = run_episode(planner, world, start, goal, np.random.default_rng(0))
    assert episode.reason == "unknown_start" and episode.detail.startswith("the start image")
    assert len(episode.actions) == 1 and not episode.success  # one action, then it stopped
    assert episode.final_state == episode.states[-1]


@pytest.mark.skipif(not (SHIPPED / "apn").is_dir(), reason="shipped model not present")
def test_shipped_model_reaches_easy_goals(world):
    import torch

    torch.set_num_threads(1)
    planner = ActionPlanner.from_model_dir(SHIPPED)
    result = evaluate_system(planner, world, world.task, pairs=5, seed=3, progress=False)
    assert result["success"] == 100.0 and result["legal_actions"] == 100.0


def shortest_path(task, start, goal):
    """States and actions of one breadth-first shortest path."""
    parent = {start: None}
    frontier = [start]
    while goal not in parent:
        nxt = []
        for s in frontier:
            for action, t in task.neighbours(s):
                if t not in parent:
                    parent[t] = (s, action)
                    nxt.append(t)
        frontier = nxt
    states, actions, s = [goal], [], goal
    while parent[s] is not None:
        s, action = parent[s]
        states.append(s)
        actions.append(action)
    return states[::-1], actions[::-1]


class SeeingWorld:
    """The world, remembering which state each rendered image showed."""

    def __init__(self, world):
        self.world, self.seen = world, {}

    def render(self):
        image = self.world.render()
        self.seen[image.tobytes()] = self.world.read_state()
        return image

    def __getattr__(self, name):
        return getattr(self.world, name)


class NodePlanner:
    """Shortest paths of the true state graph, node ids = state indices so that a PlanJudge can
    check them; `lie` swaps in a wrong first action."""

    def __init__(self, world, lie=False):
        self.world, self.lie = world, lie

    def plan(self, start, goal, max_plans=8, expect=None, avoid=()):
        task, seen = self.world.task, self.world.seen
        states, actions = shortest_path(task, seen[start.tobytes()], seen[goal.tobytes()])
        if self.lie and len(actions) > 1:
            actions = [actions[1], *actions[1:]]
        nodes = [task.all_states().index(s) for s in states]
        return [VisualActionPlan(nodes, [], actions, [1.0] * len(actions), [1] * len(actions))]


def test_table3_counts_right_plans_and_wrong_actions(world):
    from services.sim.closed_loop import PlanJudge

    task, seeing = world.task, SeeingWorld(world)
    judge = PlanJudge(task, list(task.all_states()))

    def run(lie):
        planner = NodePlanner(seeing, lie)
        return evaluate_system(planner, seeing, task, 4, seed=5, progress=False, judge=judge)

    honest = run(lie=False)["table3"]
    assert honest == {
        "system": 100.0,
        "transitions": 100.0,
        "transitions_as_seen": 100.0,
        "vfm": 100.0,
        "apn": 100.0,
    }
    liar = run(lie=True)
    assert liar["table3"]["vfm"] == 100.0  # the visual plans are right ...
    assert liar["table3"]["apn"] < 100.0  # ... their first actions are not


def test_a_step_as_seen_forgives_only_what_the_camera_could_not_see():
    from services.sim.closed_loop import PlanJudge
    from shared.tasks import get_task

    task = get_task("tshirt_folding")

    def folds(*names):
        return task.parse_state({"folds": list(names)})

    before = folds("left_sleeve", "left_side", "bottom_half")  # the sleeve under the half
    judge = PlanJudge(task, [folds("left_side", "bottom_half"), folds("left_side")])
    unfold = task.moves["unfold", "bottom_half"].action
    plan = VisualActionPlan([0, 1], [], [unfold], [1.0], [1])
    after = task.apply(before, unfold)  # the sleeve shows: folded, not as the plan guessed
    assert not judge.checker.same(judge.node_states[1], after)
    assert judge.step_as_seen(plan, before, after)
    assert not judge.step_as_seen(plan, before, folds())  # the world did another thing
    other = task.moves["unfold", "left_side"].action  # locked under the half: no such move
    assert not judge.step_as_seen(replace(plan, actions=[other]), before, after)


class WreckingWorld(SeeingWorld):
    """Its first action wrecks it: the action fails and nothing reads as a state afterwards."""

    wrecked = False

    def execute(self, action, rng):
        self.wrecked = True
        raise WorldError("the cloth matches no state")

    def read_state(self):
        if self.wrecked:
            raise WorldError("the cloth matches no state")
        return self.world.read_state()


def test_a_world_left_in_no_state_ends_the_episode_without_a_crash(world):
    start = state(world, [["red", "green"], ["blue"], ["yellow"]])
    goal = state(world, [["red"], ["green", "blue"], ["yellow"]])
    move = VisualActionPlan([0, 1], [], [Move(Cell(1, 0), Cell(1, 1))], [1.0], [1])
    episode = run_episode(FixedPlanner([move]), WreckingWorld(world), start, goal,
                          np.random.default_rng(0))  # fmt: skip
    assert episode.reason.startswith("physics:") and episode.final_state is None
    assert not episode.success


class TwoStepPlanner:
    """Two steps to go along each of two plans, from a new node each call; its shortcut is
    the action 'skip'."""

    def __init__(self):
        self.calls = 0

    def plan(self, start, goal, max_plans=8, expect=None, avoid=()):
        self.calls += 1
        n = 10 * self.calls
        return [
            VisualActionPlan([n, n + 1, n + 2], [start] * 3, ["a", "b"], [0.9] * 2, [1] * 2),
            VisualActionPlan([n, n + 3, n + 4], [start] * 3, ["c", "d"], [0.9] * 2, [1] * 2),
        ]

    def skip_first(self, plan):
        return VisualActionPlan(plan.nodes[::2], plan.images[::2], ["skip"], [0.5], [0])


def test_try_shortcuts_skips_a_share_of_the_steps_to_a_second_next_node_each_pair_once():
    image = np.zeros((8, 8, 3), np.uint8)
    never, always = TryShortcuts(TwoStepPlanner(), 0.0), TryShortcuts(TwoStepPlanner(), 1.0)
    assert never.plan(image, image)[0].actions == ["a", "b"] and not never.tried
    (taken,) = always.plan(image, image)
    assert taken.actions == ["skip"] and always.tried == {(taken.nodes[0], taken.nodes[1])}
    half = TryShortcuts(TwoStepPlanner(), 0.5, seed=3)
    tried = sum(half.plan(image, image)[0].actions == ["skip"] for _ in range(400))
    assert tried == len(half.tried) and 150 < tried < 250
    same = TwoStepPlanner()
    again = TryShortcuts(FixedPlanner(same.plan(image, image)), 1.0, tried={(10, 12)})
    again.planner.skip_first = same.skip_first
    taken = [again.plan(image, image)[0] for _ in range(2)]
    assert taken[0].nodes == [10, 14] and taken[1].actions == ["a", "b"]  # each pair once
    assert again.tried == {(10, 12), (10, 14)}
    one_step = FixedPlanner([VisualActionPlan([0, 1], [image, image], ["a"], [0.9], [1])])
    one_step.skip_first = same.skip_first
    assert TryShortcuts(one_step, 1.0).plan(image, image)[0].actions == ["a"]  # nothing to skip
    with pytest.raises(ValueError, match="share"):
        TryShortcuts(TwoStepPlanner(), 1.5)


def test_a_refused_action_ends_the_episode_unless_it_was_a_one_off_shortcut(world):
    start = state(world, [["red", "green"], ["blue"], ["yellow"]])
    goal = state(world, [["red"], ["blue"], ["yellow", "green"]])
    illegal = Move(Cell(0, 0), Cell(1, 1))  # red from under green
    with pytest.raises(IllegalActionError):
        world.task.apply(start, illegal)
    oracle = OraclePlanner(world, goal)

    class RefusedFirst:
        def __init__(self, shortcut):
            self.first, self.shortcut, self.last_was_shortcut = True, shortcut, False

        def plan(self, image, goal_image, max_plans=8, expect=None, avoid=()):
            self.last_was_shortcut = self.first and self.shortcut
            if self.first:
                self.first = False
                return [VisualActionPlan([0, 1], [image, goal_image], [illegal], [1.0], [1])]
            return oracle.plan(image, goal_image)

    rng = np.random.default_rng(0)
    stopped = run_episode(RefusedFirst(shortcut=False), world, start, goal, rng)
    assert stopped.reason == "illegal_action" and not stopped.success
    assert stopped.states == [start, start] and stopped.refused == [True]  # unchanged
    went_on = run_episode(RefusedFirst(shortcut=True), world, start, goal, rng)
    assert went_on.success and went_on.illegal_actions == 1 and len(went_on.actions) == 1
    # an ordinary plan refused under TryShortcuts ends the task rather than being repeated
    one_step = FixedPlanner([VisualActionPlan([0, 1], [], [illegal], [1.0], [1])])
    trying = run_episode(TryShortcuts(one_step, 1.0), world, start, goal, rng, max_steps=9)
    assert trying.reason == "illegal_action" and trying.illegal_actions == 1


def test_a_refused_step_is_avoided_and_a_later_plan_goes_round_it(world):
    start = state(world, [["red", "green"], ["blue"], ["yellow"]])
    goal = state(world, [["red"], ["blue"], ["yellow", "green"]])
    illegal = Move(Cell(0, 0), Cell(1, 1))  # red from under green
    oracle = OraclePlanner(world, goal)

    class AvoidingPlanner:
        def __init__(self):
            self.avoided = []

        def plan(self, image, goal_image, max_plans=8, expect=None, avoid=()):
            self.avoided.append(tuple(avoid))
            if (0, 1) in avoid:  # the honest way, by another node
                (plan,) = oracle.plan(image, goal_image)
                return [replace(plan, nodes=[0, 2][: len(plan.nodes)])]
            return [VisualActionPlan([0, 1], [image, goal_image], [illegal], [1.0], [1])]

    planner = AvoidingPlanner()
    episode = run_episode(planner, world, start, goal, np.random.default_rng(0))
    assert episode.success and episode.illegal_actions == 1 and len(episode.actions) == 1
    assert planner.avoided == [(), ((0, 1),), ((0, 1),)][: len(planner.avoided)]
    assert planner.avoided[1] == ((0, 1),)  # the refused step, given to the next plan


def test_table3_pairs_each_tried_action_with_the_state_after_it(world):
    """A refused shortcut counts as one wrong transition; the steps after it stay aligned."""
    from services.sim.closed_loop import PlanJudge

    task, seeing = world.task, SeeingWorld(world)
    never = Move(Cell(0, 0), Cell(0, 0))  # onto itself: the world refuses it from any state

    class ShortcutFirst(NodePlanner):
        last_was_shortcut = False

        def plan(self, start, goal, max_plans=8, expect=None, avoid=()):
            plans = super().plan(start, goal, max_plans, expect)
            self.last_was_shortcut = not self.last_was_shortcut and bool(plans[0].actions)
            if self.last_was_shortcut:
                plans = [replace(plans[0], actions=[never, *plans[0].actions[1:]])]
            return plans

    judge = PlanJudge(task, list(task.all_states()))
    result = evaluate_system(ShortcutFirst(seeing), seeing, task, 4, seed=5, progress=False,
                             judge=judge)  # fmt: skip
    executed, refused = result["actions_executed"], result["illegal_actions"]
    assert result["success"] == 100.0 and refused >= 4
    assert result["table3"]["transitions"] == pytest.approx(100 * executed / (executed + refused))


@pytest.mark.skipif(not (SHIPPED / "apn").is_dir(), reason="shipped model not present")
def test_skip_first_asks_the_apn_for_the_first_node_to_the_third():
    from services.apn.train import propose

    planner = ActionPlanner.from_model_dir(SHIPPED)
    roadmap = planner.planner.roadmap
    path = next(p for p in (roadmap.shortest_paths(0, g, 1)[0] for g in range(1, 60)) if len(p) > 3)
    z = roadmap.nodes[path].astype(np.float32)
    arrays, confidences = propose(planner.apn, z[:-1], z[1:])
    plan = VisualActionPlan(
        path,
        [],
        [planner.task.array_to_action(a) for a in arrays],
        list(confidences),
        [5] * (len(path) - 1),
    )
    skipped = planner.skip_first(plan)
    (straight,), _ = propose(planner.apn, z[:1], z[2:3])
    assert skipped.nodes == [path[0], *path[2:]]
    assert skipped.actions == [planner.task.array_to_action(straight), *plan.actions[2:]]
    assert skipped.supports[0] == 0 and len(skipped.confidences) == len(skipped.actions)
    with pytest.raises(ValueError, match="two steps"):
        planner.skip_first(VisualActionPlan(path[:2], [], plan.actions[:1], [0.9], [1]))


def test_an_action_budget_cuts_the_last_task_short_and_starts_no_more(world):
    never = Move(Cell(0, 0), Cell(0, 0))  # onto itself: the world refuses it from any state
    image = np.zeros((8, 8, 3), np.uint8)
    refused = FixedPlanner([VisualActionPlan([0, 1], [image, image], [never], [1.0], [1])])
    refused.last_was_shortcut = True  # a planner that may try again after a refusal
    result = evaluate_system(
        refused, world, world.task, 10, max_steps=3, progress=False, max_actions=7
    )
    assert result["pairs"] == 3 and result["illegal_actions"] == 7
    assert result["actions_executed"] == 0 and result["success"] == 0.0
