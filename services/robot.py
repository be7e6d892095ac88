"""An example robot client: asks for plans over zenoh, receives them on its plan key, acts.

The robot's body is its own MuJoCo world. After every action it looks (renders), asks
`lsr/api/plan` for a plan from what it sees to the goal, takes the plan published on
`lsr/robot/{robot_id}/plan` for that request, and executes its first action.
"""

from __future__ import annotations

import json
import logging
import queue
import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import zenoh

from services.sim.closed_loop import Episode, run_episode
from services.sim.workcell import Observer
from services.sim.worlds import make_world
from shared.appearance import task_default
from shared.bus import (
    API_PLAN_KEY,
    JSON,
    ServiceUnavailable,
    encoder_image_size,
    experience_key,
    robot_plan_key,
)
from shared.images import png_b64
from shared.plans import Match, UnknownImageError, VisualActionPlan, refused_end
from shared.tasks import get_task

log = logging.getLogger(__name__)
REPORT_EVERY = 8  # experience tuples a report (the gateway takes up to 64)


class RobotPlanner:
    """The closed loop's Planner over the public zenoh API."""

    def __init__(
        self, session: zenoh.Session, robot_id: str, task: str, timeout_s: float = 10.0
    ) -> None:
        self.session = session
        self.robot_id = robot_id
        self.task_name = task
        self.task = get_task(task)
        self.timeout_s = timeout_s
        self._plans: queue.Queue[dict[str, Any]] = queue.Queue()
        self._reports: list[dict[str, Any]] = []  # experience not yet sent
        self.reported = 0  # tuples the gateway recorded
        self.subscriber = session.declare_subscriber(
            robot_plan_key(robot_id),
            lambda sample: self._plans.put(json.loads(sample.payload.to_bytes())),
        )

    def plan(
        self,
        start: np.ndarray,
        goal: np.ndarray,
        max_plans: int = 8,
        expect: int | None = None,
        avoid: Sequence[tuple[int, int]] = (),
    ) -> list[VisualActionPlan]:
        body = {
            "task": self.task_name,
            "start": {"image": png_b64(start)},
            "goal": {"image": png_b64(goal)},
            "max_plans": max_plans,
            "robot_id": self.robot_id,
            "include_images": False,
            "expect_node": expect,
            "avoid_steps": [list(step) for step in avoid],
        }
        plan_id = self._request(body)
        published = self._published(plan_id)
        if published.get("match"):
            match = {end: Match.from_json(m) for end, m in published["match"].items()}
            end = refused_end(match)
            if end is not None:
                raise UnknownImageError(end, published.get("reason") or end, match)
        return [
            VisualActionPlan(
                nodes=p["nodes"],
                images=[],
                actions=[self.task.parse_action(a) for a in p["actions"]],
                confidences=p["confidences"],
                supports=p["supports"],
            )
            for p in published["plans"]
        ]

    def _request(self, body: dict[str, Any]) -> str:
        """The plan id of a request. A query that ends unanswered before the timeout (the mesh
        dropped it while routes changed, or no gateway was reachable yet) is asked again."""
        deadline = time.monotonic() + self.timeout_s
        pause = 0.05
        while (left := deadline - time.monotonic()) > pause:
            replies = self.session.get(
                API_PLAN_KEY,
                payload=json.dumps(body),
                encoding=JSON,
                congestion_control=zenoh.CongestionControl.BLOCK,
                timeout=left,
            )
            for reply in replies:
                if reply.ok is None and reply.err.encoding != JSON:
                    continue  # zenoh's own timeout
                if reply.ok is None:
                    error = json.loads(reply.err.payload.to_bytes())
                    if error.get("status") == 503:
                        raise ServiceUnavailable("planning", str(error.get("detail")))
                    raise RuntimeError(f"plan request refused: {error}")
                return json.loads(reply.ok.payload.to_bytes())["plan_id"]
            log.warning("no answer on %s; asking again in %.2f s", API_PLAN_KEY, pause)
            time.sleep(pause)
            pause = min(2 * pause, 1.0)  # nobody to route to yet: do not spin
        raise ServiceUnavailable("gateway", f"no answer on {API_PLAN_KEY}")

    def _published(self, plan_id: str) -> dict[str, Any]:
        """The plan as published on this robot's key (others' stale plans are skipped)."""
        deadline = time.monotonic() + self.timeout_s
        while (left := deadline - time.monotonic()) > 0:
            try:
                message = self._plans.get(timeout=left)
            except queue.Empty:
                break
            if message.get("plan_id") == plan_id:
                return message
        raise TimeoutError(f"plan {plan_id} was not published on {robot_plan_key(self.robot_id)}")

    def report(
        self, before: np.ndarray, action: Any, after: np.ndarray, *_states: Any
    ) -> int | None:
        """Keep what was done and seen (run_episode's `record`) and tell `lsr/experience/{task}`
        every REPORT_EVERY tuples (one shard per report on the gateway's side); the tuples the
        gateway holds after a report, None where nothing was sent or it could not record."""
        self._reports.append(
            {
                "before": png_b64(before),
                "action": None if action is None else self.task.action_to_json(action),
                "after": png_b64(after),
            }
        )
        return self.flush() if len(self._reports) >= REPORT_EVERY else None

    def flush(self) -> int | None:
        """Send the kept tuples (the robot goes on whatever the answer: a failure is logged)."""
        if not self._reports:
            return None
        body = {"task": self.task_name, "tuples": self._reports}
        self._reports = []
        key = experience_key(self.task_name)
        for reply in self.session.get(key, payload=json.dumps(body), encoding=JSON, timeout=5.0):
            if reply.ok is not None:
                self.reported += len(body["tuples"])
                return json.loads(reply.ok.payload.to_bytes())["total"]
            log.warning("%s: experience not recorded: %s", key, reply.err.payload.to_bytes()[:200])
            return None
        log.warning("%s: no gateway answered; experience not recorded", key)
        return None

    def close(self) -> None:
        self.subscriber.undeclare()


def run_robot(
    session: zenoh.Session,
    robot_id: str,
    task_name: str,
    start: Any,
    goal: Any,
    max_steps: int = 20,
    seed: int = 0,
    report: bool = False,
    appearance: str | None = None,
) -> Episode:
    """Reach `goal` closed loop over the public API; with `report`, every action it executes
    goes back to the gateway as experience. Its camera looks as the task's data does by
    default; at any `appearance` but clean it sends its camera's whole frames, markers and
    all, as a real cell's camera would, and the server registers them."""
    task = get_task(task_name)
    planner = RobotPlanner(session, robot_id, task_name)

    def progress(step: int, action: Any, state: Any, image: np.ndarray) -> None:
        print(
            f"[{robot_id}] step {step}: {json.dumps(task.action_to_json(action))} -> "
            f"{json.dumps(task.state_to_json(state))}",
            flush=True,
        )

    try:
        size = encoder_image_size(session, task_name, timeout_s=5.0)
        looks = appearance or task_default(task_name)
        with make_world(task_name, size, appearance=looks) as world:
            return run_episode(
                planner,
                world,
                start,
                goal,
                np.random.default_rng(seed),
                max_steps=max_steps,
                on_step=progress,
                record=planner.report if report else None,
                observer=Observer(world, register=False),
            )
    finally:
        planner.flush()
        planner.close()
        if report:
            print(f"[{robot_id}] {planner.reported} experience tuples recorded", flush=True)
