"""Closed-loop execution: act, look, re-plan from what is seen, until the goal (paper VI-B).

The planner is anything with `plan(start_image, goal_image, max_plans) -> plans`; in process it is
the ActionPlanner, in the service stack a client of the planning services.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from services.data.experience import Record, Recorder
from services.planner.evaluate import TransitionChecker, action_leads, path_verdict
from services.sim.workcell import Observer
from shared.messages import MAX_AVOID
from shared.plans import UnknownImageError, VisualActionPlan, most_confident
from shared.registration import RegistrationError
from shared.tasks.base import IllegalActionError, Task, World, WorldError, optimal_moves


class Planner(Protocol):
    """May also have `last_was_shortcut`: True when its last plan was a one-off try
    (TryShortcuts), after whose refusal the loop plans again rather than stopping."""

    def plan(
        self,
        start: np.ndarray,
        goal: np.ndarray,
        max_plans: int = ...,
        expect: int | None = ...,
        avoid: Sequence[tuple[int, int]] = ...,
    ) -> list[VisualActionPlan]:
        """`expect`: the node the loop's last step was meant to reach (knowing.keep_place);
        `avoid`: steps (from node, to node) whose action led elsewhere in this task."""
        ...


class ShortcutPlanner(Planner, Protocol):
    def skip_first(self, plan: VisualActionPlan) -> VisualActionPlan:
        """`plan` with its first two steps as one action (ActionPlanner.skip_first)."""
        ...


class TryShortcuts:
    """Plans as `planner` does, but a `share` of the steps try a shortcut: the APN's action
    from here straight to the second next node of one of the plans, each pair of nodes once
    (`tried`, which may be kept across roadmap versions: built nodes keep their ids). Ordinary
    tasks re-walk the roadmap's own edges and so teach it nothing new; a tried shortcut either
    shows a move the data never did or, landing elsewhere, another one (new edges once grown),
    or is refused; the closed loop re-plans from what it sees. `last_was_shortcut` tells the
    loop whether the plan just given was such a try, which a refusal does not end the task for."""

    def __init__(
        self,
        planner: ShortcutPlanner,
        share: float,
        seed: int = 0,
        tried: set[tuple[int, int]] | None = None,
    ) -> None:
        if not 0.0 <= share <= 1.0:
            raise ValueError(f"share must lie in [0, 1], got {share}")
        self.planner = planner
        self.share = share
        self.rng = np.random.default_rng(seed)
        self.tried = set() if tried is None else tried
        self.last_was_shortcut = False

    def plan(
        self,
        start: np.ndarray,
        goal: np.ndarray,
        max_plans: int = 8,
        expect: int | None = None,
        avoid: Sequence[tuple[int, int]] = (),
    ) -> list[VisualActionPlan]:
        self.last_was_shortcut = False
        plans = self.planner.plan(start, goal, max_plans, expect=expect, avoid=avoid)
        options = {(p.nodes[0], p.nodes[2]): p for p in plans if len(p.nodes) > 2}
        fresh = sorted(pair for pair in options if pair not in self.tried)
        if not fresh or self.rng.random() >= self.share:
            return plans
        pair = fresh[self.rng.integers(len(fresh))]
        self.tried.add(pair)
        self.last_was_shortcut = True
        return [self.planner.skip_first(options[pair])]


@dataclass
class Episode:
    success: bool
    # "goal", "unreachable", "planner_at_goal", "illegal_action", "max_steps", "unknown_start"
    # (the observed scene), "unknown_goal", ...
    reason: str
    final_state: Any  # None when the world reads as no valid state at the end
    actions: list[Any] = field(default_factory=list)
    images: list[np.ndarray] = field(default_factory=list)  # observed after each action
    illegal_actions: int = 0
    detail: str | None = None  # the planner's words, where it refused
    # For the paper's Table III: the plans of every planning step, the plan acted on at each,
    # and the start state then the state after each action tried (unchanged when refused).
    plans: list[list[VisualActionPlan]] = field(default_factory=list)
    chosen: list[VisualActionPlan] = field(default_factory=list)
    states: list[Any] = field(default_factory=list)
    refused: list[bool] = field(default_factory=list)  # for each action tried


def run_episode(
    planner: Planner,
    world: World,
    start: Any,
    goal: Any | None,
    rng: np.random.Generator,
    goal_image: np.ndarray | None = None,
    max_steps: int = 20,
    max_plans: int = 8,
    on_step: Callable[[int, Any, Any, np.ndarray], None] | None = None,
    record: Record | None = None,
    observer: Observer | None = None,
) -> Episode:
    """Start from a fresh render of `start`; `goal` as a state, or only as `goal_image`.

    `on_step(step, action, state, image)` is told of every executed action and the image
    recorded after it (progress for robots; a camera-like world draws each image once).
    `observer` is how the world's images reach the planner (services.sim.workcell.Observer;
    by default registered here). `record` gets every executed action as experience (the
    image planned from, the action, the image after), a refused one and each fresh look at an
    unchanged scene as no-action pairs. A step whose action the world refused, or whose action
    led elsewhere (the next plan does not start at the node it was meant to reach), is given
    to every later plan of the task as a step to avoid; a plan that takes a refused step again
    (no way left without it) ends the episode rather than repeat it. A refused one-off try
    (the planner's `last_was_shortcut`: TryShortcuts, which will not give it again) is not.
    """
    # every image registered to the table frame, as a cell's are (here, or by the server)
    observer = observer or Observer(world)
    try:
        if goal_image is None:
            if goal is None:
                raise ValueError("give the goal as a state or as an image")
            world.reset(goal, rng)
            goal_image = observer.see()
        else:
            goal_image = observer.table_frame(goal_image)
    except RegistrationError as exc:
        state = world.reset(start, rng)
        return Episode(
            success=False,
            reason="unknown_goal",
            final_state=state,
            states=[state],
            detail=f"the goal image is not known: {exc}",
        )
    state = world.reset(start, rng)
    episode = Episode(success=False, reason="max_steps", final_state=state, states=[state])
    last: np.ndarray | None = None  # the image seen after the last action
    expect: int | None = None  # the node the last step was meant to reach
    step: tuple[int, int] | None = None  # that step, from node to node
    missed: list[tuple[int, int]] = []  # steps whose action led elsewhere or was refused
    refused_steps: set[tuple[int, int]] = set()
    looks = world.task.view  # the goal is reached when the scene shows its view
    for _ in range(max_steps):
        if goal is not None and looks(state) == looks(goal):
            break
        try:
            seen = observer.see()
        except RegistrationError as exc:  # a robot that cannot see the markers does not act
            episode.reason, episode.detail = "unknown_start", f"the start image is not known: {exc}"
            break
        if record is not None and last is not None and not np.array_equal(last, seen):
            record(last, None, seen, state, state)
        try:
            plans = planner.plan(
                seen, goal_image, max_plans, expect=expect, avoid=missed[-MAX_AVOID:]
            )
            if step is not None and plans and plans[0].nodes[0] != expect and step not in missed:
                missed.append(step)  # its action led elsewhere: no plan of this task takes it
                if any(tuple(p.nodes[:2]) == step for p in plans):
                    plans = planner.plan(
                        seen, goal_image, max_plans, expect=expect, avoid=missed[-MAX_AVOID:]
                    )
        except UnknownImageError as refused:  # never act on a scene the model does not know
            episode.reason = f"unknown_{refused.end}"
            episode.detail = refused.reason
            break
        episode.plans.append(plans)
        if not plans:
            episode.reason = "unreachable"
            break
        plan = most_confident(plans)
        if tuple(plan.nodes[:2]) in refused_steps:  # no way left but a step the world refused
            episode.reason = "illegal_action"
            break
        episode.chosen.append(plan)
        if not plan.actions:  # the planner sees start and goal in one region
            episode.reason = "planner_at_goal"
            break
        if plan.actions[0] is None:  # the APN saw no action between the first two nodes
            episode.reason = "no_action"
            break
        before = state
        try:
            state = world.execute(plan.actions[0], rng)
        except IllegalActionError:
            episode.illegal_actions += 1
            episode.states.append(state)
            episode.refused.append(True)
            if record is not None:
                after, why = observer.look()
                if why is None:
                    record(seen, None, after, state, state)
            if getattr(planner, "last_was_shortcut", False) is True:
                continue
            refused_steps.add((plan.nodes[0], plan.nodes[1]))
            if (plan.nodes[0], plan.nodes[1]) not in missed:
                missed.append((plan.nodes[0], plan.nodes[1]))  # no later plan of the task takes it
            continue
        except WorldError as exc:
            episode.reason = f"physics: {exc}"
            break
        expect = plan.nodes[1]
        step = (plan.nodes[0], expect)
        episode.actions.append(plan.actions[0])
        episode.states.append(state)
        episode.refused.append(False)
        last, why = observer.look()  # a frame not registered: shown, not recorded
        episode.images.append(last)
        if record is not None and why is None:
            record(seen, plan.actions[0], last, before, state)
        if on_step is not None:
            on_step(len(episode.actions), plan.actions[0], state, episode.images[-1])
    try:
        episode.final_state = world.read_state()
    except WorldError:  # the action left the world in no valid state (a wrecked cloth, say)
        episode.final_state = None
    final = episode.final_state
    episode.success = goal is not None and final is not None and looks(final) == looks(goal)
    if goal is None:
        episode.success = episode.reason == "planner_at_goal"
    if episode.success:
        episode.reason = "goal"
    return episode


class PlanJudge:
    """Judges plans by the views their roadmap nodes stand for (each node's majority view),
    as interface.md's "Views" says."""

    def __init__(self, task: Task, node_states: list[Any]) -> None:
        self.task = task
        self.node_states = node_states
        self.checker = TransitionChecker(task)

    def visual_plan_ok(self, plan: VisualActionPlan, start: Any, goal: Any) -> bool:
        """The nodes look like the start, then the goal at the end, and a chain of legal moves
        runs through them."""
        states = [self.node_states[n] for n in plan.nodes]
        return path_verdict(self.checker, states, start, goal)[0]

    def action_plan_ok(self, plan: VisualActionPlan) -> bool:
        """The actions, applied by the rules from a state looking like the first node, pass
        through states looking like the next nodes."""
        states = [self.node_states[n] for n in plan.nodes]
        return self.checker.actions_lead(states, plan.actions)

    def step_as_seen(self, plan: VisualActionPlan, before: Any, after: Any) -> bool:
        """The step ended where the plan's next node shows, or differs from it only in what
        the camera could not see before the move: the action leads there from some state
        showing what it saw, and the world made the rules' move (a sleeve under the folded
        half shows which way it lay only once the half is unfolded). Where nothing hides,
        the same as the next node's view alone."""
        expected = self.node_states[plan.nodes[1]]
        if self.checker.same(expected, after):
            return True
        try:
            made = self.task.apply(before, plan.actions[0]) == after
        except IllegalActionError:
            return False
        return made and action_leads(self.checker, before, plan.actions[0], expected)


def evaluate_system(
    planner: Planner,
    world: World,
    task: Task,
    pairs: int,
    seed: int = 0,
    max_steps: int = 20,
    progress: bool = True,
    judge: PlanJudge | None = None,
    record: Recorder | None = None,
    max_actions: int | None = None,
    head_camera: bool = False,
) -> dict[str, Any]:
    """Random start/goal state pairs run closed loop (goals that look unlike the start);
    success = the simulator reaches a state that shows the goal's view.
    `max_actions`: a budget of actions tried (legal or refused); the task that reaches it is
    cut short and no further task starts ("pairs" says how many ran). `head_camera`: the
    camera's pose drawn anew for every image of an episode (a robot's head camera).

    With a `judge`, also the paper's Table III: correct single transitions (the state after an
    action tried looks like the plan's next node; a refused one never does; and beside it,
    `transitions_as_seen`, by what the camera showed before the move), VFM success
    (some visual plan of the first planning step is correct) and APN success (the chosen
    plan's actions all are).
    """
    from tqdm import tqdm

    rng = np.random.default_rng(seed)
    successes = steps_on_success = optimal_on_success = executed = illegal = 0
    right_transitions = seen_transitions = vfm_ok = apn_ok = 0
    reasons: dict[str, int] = {}
    ran = 0
    for _ in tqdm(range(pairs), desc="closed loop", unit="pair", disable=not progress):
        steps = (
            max_steps if max_actions is None else min(max_steps, max_actions - executed - illegal)
        )
        if steps <= 0:
            break
        ran += 1
        start = task.sample_state(rng)
        goal = task.sample_state(rng)
        while task.view(goal) == task.view(start):
            goal = task.sample_state(rng)
        observer = Observer(world, moving=head_camera)  # as a cell's: its own registration
        episode = run_episode(
            planner, world, start, goal, rng, max_steps=steps, record=record, observer=observer
        )
        executed += len(episode.actions)
        illegal += episode.illegal_actions
        reasons[episode.reason] = reasons.get(episode.reason, 0) + 1
        if episode.success:
            successes += 1
            steps_on_success += len(episode.actions)
            optimal_on_success += optimal_moves(task, start, goal) or 0
        if judge is not None:
            first = episode.plans[0] if episode.plans else []
            vfm_ok += any(judge.visual_plan_ok(p, start, goal) for p in first)
            apn_ok += bool(episode.chosen) and judge.action_plan_ok(episode.chosen[0])
            tried = zip(
                episode.chosen, episode.states, episode.states[1:], episode.refused, strict=False
            )
            for plan, before, after, refused in tried:
                right = not refused and judge.checker.same(judge.node_states[plan.nodes[1]], after)
                right_transitions += right
                seen_transitions += right or (
                    not refused and judge.step_as_seen(plan, before, after)
                )
    if record is not None:
        record.flush()
    attempted = executed + illegal
    result = {
        "pairs": ran,
        "success": 100.0 * successes / ran if ran else 0.0,
        "mean_steps": steps_on_success / successes if successes else None,
        "mean_optimal_steps": optimal_on_success / successes if successes else None,
        "steps_over_optimal": steps_on_success / optimal_on_success if optimal_on_success else None,
        "legal_actions": 100.0 * executed / attempted if attempted else None,
        "actions_executed": executed,
        "illegal_actions": illegal,
        "outcomes": dict(sorted(reasons.items())),
        "max_steps": max_steps,
        "seed": seed,
    }
    if judge is not None:
        result["table3"] = {
            "system": result["success"],
            "transitions": 100.0 * right_transitions / attempted if attempted else None,
            # a sleeve the camera could not see before the move not held against the plan
            "transitions_as_seen": 100.0 * seen_transitions / attempted if attempted else None,
            "vfm": 100.0 * vfm_ok / ran if ran else None,
            "apn": 100.0 * apn_ok / ran if ran else None,
        }
    return result
