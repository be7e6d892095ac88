"""What the gateway does for each route, over zenoh; the FastAPI routes only wrap these."""

from __future__ import annotations

import base64
import binascii
import json
import time
import uuid
from dataclasses import replace
from typing import Any

import numpy as np
import zenoh

from services.data.experience import ExperienceLog
from services.gateway.schemas import (
    Endpoint,
    ExecuteRequest,
    ExecuteResponse,
    ExecuteStep,
    ExperienceRequest,
    ExperienceResponse,
    Health,
    Instance,
    Plan,
    PlanRequest,
    PlanResponse,
    RenderRequest,
    RenderResponse,
    ServiceHealth,
)
from shared.bus import (
    JSON,
    SERVICES,
    CallTiming,
    ServiceUnavailable,
    instances,
    robot_plan_key,
)
from shared.client import FrameRefused, Image, PlanningClient
from shared.dataset import DatasetError
from shared.images import ImageError, PngCache, decode_image, png_b64
from shared.messages import RunRequest
from shared.settings import Settings
from shared.tasks import declare_task, get_task, has_simulator
from shared.tasks.base import TaskError
from shared.tasks.spec import TaskSpec
from shared.validation import FieldError, frame_size, parse_state


class TaskNotServed(LookupError):
    """A known task that no service of this deployment serves (404, not a 503 after a wait)."""

    def __init__(self, task: str, served: list[str]) -> None:
        super().__init__(f"task {task!r} is not served here; served tasks are {served}")


def b64_bytes(field: str, text: str) -> bytes:
    """The bytes of base64 text (a data URL's too), or a FieldError naming `field`."""
    if text.startswith("data:"):
        text = text.partition(",")[2]
    try:
        return base64.b64decode(text, validate=True)
    except (binascii.Error, ValueError):
        raise FieldError(field, "not valid base64") from None


def decode_b64_image(field: str, text: str, size: int) -> np.ndarray:
    """A base64 PNG/JPEG of `size` pixels a side."""
    try:
        return decode_image(b64_bytes(field, text), size)
    except ImageError as exc:
        raise FieldError(field, str(exc)) from None


def image_input(field: str, text: str, size: int) -> np.ndarray | bytes:
    """A base64 image as it goes on: pixels for an image at the model's `size` (a view in the
    table frame, a few kB), else a camera frame's bytes as the client sent them, checked from
    their header only (format, sides, decoded pixels: a decode bomb is refused here, naming
    `field`); the encoder decodes and registers it."""
    data = b64_bytes(field, text)
    if frame_size(field, data) == (size, size):
        try:
            return decode_image(data, size)
        except ImageError as exc:
            raise FieldError(field, str(exc)) from None
    return data


class Gateway:
    def __init__(self, session: zenoh.Session, settings: Settings) -> None:
        self.session = session
        self.settings = settings
        self._clients: dict[str, PlanningClient] = {}
        self.pngs = PngCache()
        self._logs: dict[str, ExperienceLog] = {}  # task -> where its robots' reports go
        for spec in settings.task_specs.values():  # tasks defined by their data
            declare_task(TaskSpec.from_json(spec))

    def services(self, task: str) -> tuple[str, ...]:
        """The services that serve `task`: no sim for a task without a simulator."""
        return SERVICES if has_simulator(task) else tuple(s for s in SERVICES if s != "sim")

    def simulated(self, task: str, route: str) -> str:
        """`task` when it is served and has a simulator; a FieldError on `task` otherwise."""
        self.served(task)
        if not has_simulator(task):
            raise FieldError(
                "task",
                f"task {task!r} has no simulator (it is defined by its data): {route} needs "
                "one; /plan works with images as start and goal",
            )
        return task

    def served(self, task: str) -> str:
        if task not in self.settings.tasks:
            raise TaskNotServed(task, self.settings.tasks)
        return task

    def client(self, task: str) -> PlanningClient:
        self.served(task)
        if task not in self._clients:
            self._clients[task] = PlanningClient(self.session, task, self.settings.deadline_s)
        return self._clients[task]

    def image_size(self, task: str, deadline: float) -> int:
        """The model's image size, asked of the encoder and remembered for a few seconds."""
        return self.client(task).image_size(deadline)

    def health(self) -> Health:
        asked = {
            (service, task): instances(self.session, service, task)
            for task in self.settings.tasks
            for service in self.services(task)
        }  # all in flight at once
        found = {key: collect() for key, collect in asked.items()}
        services: dict[str, ServiceHealth] = {}
        for service in SERVICES:
            per_task = [found[(service, t)] for t in self.settings.tasks if (service, t) in found]
            services[service] = ServiceHealth(
                status="ok" if all(per_task) else "unavailable",
                instances=[
                    Instance(
                        instance=i.instance,
                        task=i.task,
                        model_id=i.model_id,
                        uptime_s=i.uptime_s,
                        roadmap_version=i.roadmap_version,
                    )
                    for infos in per_task
                    for i in infos
                ],
            )
        down = [name for name, s in services.items() if s.status != "ok"]
        if down:
            return Health(status="unavailable", services=services, detail=f"down: {down}")
        models = {(i.task, i.model_id) for infos in found.values() for i in infos}
        if len({task for task, _ in models}) != len(models):
            detail = "services serve different models"
            return Health(status="inconsistent", services=services, detail=detail)
        return Health(status="ok", services=services)

    # routes ---------------------------------------------------------------------------------
    def _images(
        self, task: str, endpoints: dict[str, Endpoint], deadline: float
    ) -> dict[str, Image]:
        """The image endpoints (`image_input`: camera frames go on compressed, to be registered
        by the encoder; images at the model's size are in the table frame already), and the
        state endpoints rendered (in one sim call)."""
        logic = get_task(task)
        images: dict[str, Image] = {}
        states = {}
        size = None
        for name, endpoint in endpoints.items():
            if endpoint.image is not None:
                size = size or self.image_size(task, deadline)
                images[name] = image_input(f"{name}.image", endpoint.image, size)
            else:
                states[name] = parse_state(logic, f"{name}.state", endpoint.state)
        if states:
            rendered = self.client(task).render(list(states.values()), 0, deadline)
            images.update(zip(states, rendered, strict=True))
        return images

    def plan(self, request: PlanRequest, deadline: float | None = None) -> tuple[PlanResponse, str]:
        """The plans, and where the time went as a Server-Timing header value.

        Every service call of the request shares one deadline (`time.monotonic()`; by default
        LSR_DEADLINE_S from now), so that a hang anywhere costs the caller that budget once.
        """
        started = time.perf_counter()
        self.served(request.task)
        deadline = deadline or time.monotonic() + self.settings.deadline_s
        endpoints = {"start": request.start, "goal": request.goal}
        images = self._images(request.task, endpoints, deadline)
        client = self.client(request.task)
        try:
            outcome = client.plan_with_reason(
                images["start"],
                images["goal"],
                request.max_plans,
                request.include_images,
                deadline,
                request.expect_node,
                request.avoid_steps,
            )
        except FrameRefused as exc:  # decoded only in the encoder: named here
            raise FieldError(f"{['start', 'goal'][exc.index]}.image", str(exc)) from None
        response = PlanResponse(
            plan_id=uuid.uuid4().hex,
            plans=[
                Plan(
                    images=[self.pngs.b64(image) for image in plan.images],
                    **plan.to_json(client.task),
                )
                for plan in outcome.plans
            ],
            reason=outcome.reason,
            match=None
            if outcome.match is None
            else {end: found.to_json() for end, found in outcome.match.items()},
        )
        if request.robot_id is not None:
            self.session.put(
                robot_plan_key(request.robot_id),
                response.model_dump_json(),
                encoding=JSON,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
        return response, server_timing(outcome.timings, (time.perf_counter() - started) * 1e3)

    def render(self, request: RenderRequest, deadline: float | None = None) -> RenderResponse:
        task = get_task(self.simulated(request.task, "/render"))
        state = parse_state(task, "state", request.state)
        deadline = deadline or time.monotonic() + self.settings.deadline_s
        client = self.client(request.task)
        image = client.render([state], request.seed, deadline, request.appearance, request.frame)[0]
        return RenderResponse(image=png_b64(image))

    def run_request(self, request: ExecuteRequest, progress: str | None = None) -> RunRequest:
        """The sim's request for an execution, checked here so that bad input (or a task with
        no simulator) gets a 4xx before anything runs; `progress` names a step stream."""
        logic = get_task(self.simulated(request.task, "/execute"))
        start = parse_state(logic, "start.state", request.start.state)
        goal_state = goal_image = None
        if request.goal.state is not None:
            goal_state = logic.state_to_json(parse_state(logic, "goal.state", request.goal.state))
        else:  # a frame is registered by the episode, as its own observations are; it
            # crosses the bus as the client's bytes, checked here from its header
            goal_image = b64_bytes("goal.image", request.goal.image)
            frame_size("goal.image", goal_image)
        return RunRequest(
            task=request.task,
            start=logic.state_to_json(start),
            goal_state=goal_state,
            goal_image=goal_image,
            max_steps=request.max_steps,
            max_plans=request.max_plans,
            seed=request.seed,
            progress=progress,
            appearance=request.appearance,
        )

    def record(
        self, request: ExperienceRequest, deadline: float | None = None
    ) -> ExperienceResponse:
        """Append a robot's reported actions to the task's experience folder (images in the
        table frame at the model's size, camera frames registered by the encoder first; no
        states: a robot does not know them)."""
        task = self.served(request.task)
        if self.settings.experience_dir is None:
            raise ServiceUnavailable("experience", "not recorded here: LSR_EXPERIENCE_DIR is unset")
        deadline = deadline or time.monotonic() + self.settings.deadline_s
        size = self.image_size(task, deadline)
        logic = get_task(task)
        before, after, actions = [], [], []
        for i, row in enumerate(request.tuples):
            before.append(self._table_frame(task, f"tuples.{i}.before", row.before, size, deadline))
            after.append(self._table_frame(task, f"tuples.{i}.after", row.after, size, deadline))
            try:
                action = None if row.action is None else logic.parse_action(row.action)
            except TaskError as exc:
                raise FieldError(f"tuples.{i}.action", str(exc)) from None
            actions.append(logic.action_to_array(action))
        folder = self.settings.experience_dir / task
        try:
            log = self._logs.get(task)
            if log is None or log.image_size != size:  # opened (and checked) once per model
                spec = replace(logic.spec, state=None)
                log = self._logs[task] = ExperienceLog(folder, spec, size, source="robots")
            total = log.append(np.stack(before), np.stack(after), np.stack(actions))
        except (OSError, DatasetError) as exc:  # unwritable, full, or a damaged manifest
            raise ServiceUnavailable("experience", f"not recordable in {folder}: {exc}") from exc
        return ExperienceResponse(recorded=len(actions), total=total)

    def _table_frame(
        self, task: str, field: str, text: str, size: int, deadline: float
    ) -> np.ndarray:
        """A reported image at the model's size; a camera frame registered by the encoder (a
        FieldError naming `field` when its markers are not found)."""
        image = image_input(field, text, size)
        if isinstance(image, np.ndarray):
            return image
        try:
            (registered,), (why,) = self.client(task).register([image], deadline)
        except FrameRefused as exc:
            raise FieldError(field, str(exc)) from None
        if why is not None:
            raise FieldError(field, why)
        return registered

    def execute(self, request: ExecuteRequest) -> ExecuteResponse:
        run = self.run_request(request)
        deadline = self.settings.deadline_s + self.settings.execute_step_s * request.max_steps
        reply = self.client(request.task).run(run, deadline)
        return ExecuteResponse(
            success=reply.success,
            reason=reply.reason,
            detail=reply.detail,
            final_state=reply.final_state,
            final_view=reply.final_view,
            steps=[
                ExecuteStep(action=action, image=png_b64(image))
                for action, image in zip(reply.actions, reply.images.numpy(), strict=True)
            ],
        )


def server_timing(calls: list[CallTiming], total_ms: float) -> str:
    """`encode;dur=8.1, encode-handler;dur=6.9, ..., gateway;dur=17.2`: round trips of the
    service calls, their handlers' own time, and the gateway's whole time (browsers show it).

    Propose and decode run at once and are read in that order: decode's round trip, when there
    is one, includes any wait for propose."""
    metrics = []
    for call in calls:
        metrics.append(f"{call.operation};dur={call.round_trip_ms:.2f}")
        if call.handler_ms is not None:
            metrics.append(f"{call.operation}-handler;dur={call.handler_ms:.2f}")
    metrics.append(f"gateway;dur={total_ms:.2f}")
    return ", ".join(metrics)


def plan_query_error(status: int, detail: Any) -> bytes:
    """The reply_err payload of `lsr/api/plan`: the REST status and body, as JSON."""
    return json.dumps({"status": status, "detail": detail}).encode()
