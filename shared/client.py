"""A client of the planning services over zenoh: what the gateway, the sim and robots call.

`plan()` does the work of the in-process ActionPlanner (encode, roadmap search, decode, APN) as
queries: encode and search one after the other, then decoding and action proposal in parallel.
"""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np
import zenoh
from pydantic import BaseModel

from shared.bus import PendingCall, Replicas, call
from shared.messages import (
    DecodeReply,
    DecodeRequest,
    EncodeReply,
    EncodeRequest,
    M,
    PathsReply,
    PathsRequest,
    ProposeReply,
    ProposeRequest,
    RenderReply,
    RenderRequest,
    RunReply,
    RunRequest,
    WireArray,
)
from shared.plans import VisualActionPlan
from shared.tasks import get_task


class PlanningClient:
    def __init__(self, session: zenoh.Session, task: str, deadline_s: float = 4.5) -> None:
        self.session = session
        self.task_name = task
        self.task = get_task(task)
        self.deadline_s = deadline_s
        self.replicas = Replicas(session)

    def _call(
        self,
        service: str,
        operation: str,
        request: BaseModel,
        reply_type: type[M],
        deadline_s: float | None = None,
    ) -> PendingCall:
        return call(
            self.session,
            service,
            self.task_name,
            operation,
            request,
            reply_type,
            deadline_s=deadline_s or self.deadline_s,
            replicas=self.replicas,
        )

    def render(self, states: list[Any], seed: int = 0) -> np.ndarray:
        request = RenderRequest(
            task=self.task_name, states=[self.task.state_to_json(s) for s in states], seed=seed
        )
        reply: RenderReply = self._call("sim", "render", request, RenderReply).result()
        return reply.images.numpy()

    def encode(self, images: np.ndarray) -> np.ndarray:
        request = EncodeRequest(task=self.task_name, images=WireArray.of(images))
        reply: EncodeReply = self._call("encoder", "encode", request, EncodeReply).result()
        return reply.latents.numpy()

    def plan_with_reason(
        self, start: np.ndarray, goal: np.ndarray, max_plans: int = 8, include_images: bool = True
    ) -> tuple[list[VisualActionPlan], str | None]:
        z_start, z_goal = self.encode(np.stack([start, goal]))
        search = PathsRequest(
            task=self.task_name,
            z_start=WireArray.of(z_start),
            z_goal=WireArray.of(z_goal),
            max_plans=max_plans,
        )
        found: PathsReply = self._call("planner", "paths", search, PathsReply).result()
        if not found.paths:
            return [], found.reason
        latents = dict(zip(found.node_ids, found.node_latents.numpy(), strict=True))
        steps = list(dict.fromkeys((a, b) for p in found.paths for a, b in itertools.pairwise(p)))
        proposing = decoding = None
        if steps:
            propose = ProposeRequest(
                task=self.task_name,
                z_from=WireArray.of(np.stack([latents[a] for a, _ in steps])),
                z_to=WireArray.of(np.stack([latents[b] for _, b in steps])),
            )
            proposing = self._call("apn", "propose", propose, ProposeReply)
        if include_images:
            decode = DecodeRequest(task=self.task_name, latents=found.node_latents)
            decoding = self._call("encoder", "decode", decode, DecodeReply)
        proposed: dict[tuple[int, int], tuple[Any, float]] = {}
        if proposing is not None:
            reply: ProposeReply = proposing.result()
            for step, action, confidence in zip(
                steps, reply.actions, reply.confidences, strict=True
            ):
                parsed = None if action is None else self.task.parse_action(action)
                proposed[step] = (parsed, confidence)
        images: dict[int, np.ndarray] = {}
        if decoding is not None:
            decoded: DecodeReply = decoding.result()
            images = dict(zip(found.node_ids, decoded.images.numpy(), strict=True))
        plans = []
        for path in found.paths:
            pairs = [proposed[(a, b)] for a, b in itertools.pairwise(path)]
            if any(action is None for action, _ in pairs):
                continue  # the APN saw no action between two nodes: not a plan a robot can run
            plans.append(
                VisualActionPlan(
                    nodes=path,
                    images=[images[n] for n in path] if include_images else [],
                    actions=[action for action, _ in pairs],
                    confidences=[confidence for _, confidence in pairs],
                )
            )
        return plans, None if plans else "the APN proposed no action for a step of every path"

    def plan(
        self, start: np.ndarray, goal: np.ndarray, max_plans: int = 8, include_images: bool = False
    ) -> list[VisualActionPlan]:
        """The closed loop's Planner protocol: plans only, no decoded images unless asked."""
        return self.plan_with_reason(start, goal, max_plans, include_images)[0]

    def run(self, request: RunRequest, deadline_s: float) -> RunReply:
        """A closed-loop episode in a sim instance; it plans through this same network."""
        return self._call("sim", "run", request, RunReply, deadline_s=deadline_s).result()
