"""A client of the planning services over zenoh: what the gateway, the sim and robots call.

`plan()` does the work of the in-process ActionPlanner (encode, roadmap search, decode, APN) as
queries: encode and search one after the other, then decoding and action proposal in parallel.
Like the ActionPlanner, it decodes each roadmap node once: the images are kept by model and latent.
"""

from __future__ import annotations

import dataclasses
import itertools
import time
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
import zenoh
from pydantic import BaseModel

from shared.bus import (
    CallTiming,
    PendingCall,
    RemoteError,
    Replicas,
    call,
    encoder_image_size,
)
from shared.images import encode_frame
from shared.lru import LruCache
from shared.messages import (
    DecodeReply,
    DecodeRequest,
    EncodeReply,
    EncodeRequest,
    FramesRequest,
    M,
    PathsReply,
    PathsRequest,
    ProposeReply,
    ProposeRequest,
    RegisterReply,
    RenderReply,
    RenderRequest,
    RunReply,
    RunRequest,
    WireArray,
)
from shared.plans import Match, UnknownImageError, VisualActionPlan, refused_end
from shared.tasks import get_task

# An image a client gives: pixels (views at the model's size; plan() compresses a camera's
# frames first), or a camera frame's PNG/JPEG bytes as its camera or client gave them
Image = np.ndarray | bytes
SIZE_TTL_S = 10.0  # a model's image size is asked again after this long (a new model)


class FrameRefused(ValueError):
    """A camera frame the encoder could not decode; `index`: its place among the images given
    (the gateway names the field of it)."""

    def __init__(self, index: int, message: str) -> None:
        super().__init__(message)
        self.index = index

    @classmethod
    def of(cls, exc: RemoteError, rows: list[int]) -> RemoteError | FrameRefused:
        """The frame `exc` names (`frames.K`, K among `rows`), or `exc` when it names none."""
        field = exc.error.field or ""
        k = field.removeprefix("frames.")
        if exc.error.code != "bad_request" or not field.startswith("frames.") or not k.isdigit():
            return exc
        message = exc.error.message.removeprefix(f"{field}: ")
        return cls(rows[int(k)], message) if int(k) < len(rows) else exc


class PlanOutcome(NamedTuple):
    plans: list[VisualActionPlan]
    reason: str | None  # why there are no plans
    timings: list[CallTiming]  # the service calls it took, in order
    match: dict[str, Match] | None = None  # how well the model knows each end


class PlanningClient:
    def __init__(self, session: zenoh.Session, task: str, deadline_s: float = 4.5) -> None:
        self.session = session
        self.task_name = task
        self.task = get_task(task)
        self.deadline_s = deadline_s
        self.replicas = Replicas(session)
        self.node_images: LruCache[tuple[str, bytes], np.ndarray] = LruCache()
        self._size: tuple[float, int] | None = None  # (when asked, the model's image size)

    def _call(
        self,
        service: str,
        operation: str,
        request: BaseModel,
        reply_type: type[M],
        deadline: float,
    ) -> PendingCall:
        return call(
            self.session,
            service,
            self.task_name,
            operation,
            request,
            reply_type,
            deadline_s=deadline - time.monotonic(),
            replicas=self.replicas,
        )

    def deadline(self) -> float:
        """The default deadline of a request begun now (`time.monotonic()` seconds)."""
        return time.monotonic() + self.deadline_s

    def render(
        self,
        states: list[Any],
        seed: int = 0,
        deadline: float | None = None,
        appearance: str | None = None,
        frame: bool = False,
    ) -> np.ndarray:
        """Images of `states`; `appearance` None: the served model's training appearance;
        `frame`: the cell camera's whole frames (markers and all), not the table-frame view."""
        request = RenderRequest(
            task=self.task_name,
            states=[self.task.state_to_json(s) for s in states],
            seed=seed,
            appearance=appearance,
            frame=frame,
        )
        rendering = self._call("sim", "render", request, RenderReply, deadline or self.deadline())
        reply: RenderReply = rendering.result()
        return reply.images.numpy()

    def image_size(self, deadline: float | None = None) -> int:
        """The served model's image size, asked of the encoder and remembered for a while."""
        if self._size is None or time.monotonic() - self._size[0] > SIZE_TTL_S:
            left = (deadline or self.deadline()) - time.monotonic()
            self._size = (
                time.monotonic(),
                encoder_image_size(self.session, self.task_name, max(0.05, min(1.5, left))),
            )
        return self._size[1]

    def register(
        self, frames: list[Image], deadline: float | None = None
    ) -> tuple[np.ndarray, list[str | None]]:
        """`frames` (PNG/JPEG bytes, or pixels) in the table frame at the model's size, and why
        each that could not be registered was not (None where it was)."""
        sent = [f if isinstance(f, bytes) else encode_frame(f) for f in frames]
        request = FramesRequest(task=self.task_name, frames=sent)
        registering = self._call(
            "encoder", "register", request, RegisterReply, deadline or self.deadline()
        )
        try:
            reply: RegisterReply = registering.result()
        except RemoteError as exc:
            raise FrameRefused.of(exc, list(range(len(frames)))) from None
        return reply.images.numpy(), reply.refused or [None] * len(frames)

    def _encode(
        self, images: list[Image], deadline: float
    ) -> tuple[np.ndarray, WireArray | None, list[str | None], list[PendingCall]]:
        """Latents, reconstruction errors and registration refusals of `images`: pixels (views
        at the model's size) in one `encode` call, camera frames' bytes in one `frames` call,
        both in flight at once."""
        frames = [image if isinstance(image, bytes) else None for image in images]
        groups = {
            "encode": [i for i, f in enumerate(frames) if f is None],
            "frames": [i for i, f in enumerate(frames) if f is not None],
        }
        requests = {
            "encode": lambda rows: EncodeRequest(
                task=self.task_name, images=WireArray.of(np.stack([images[i] for i in rows]))
            ),
            "frames": lambda rows: FramesRequest(
                task=self.task_name, frames=[frames[i] for i in rows]
            ),
        }
        pending = {
            operation: self._call(
                "encoder", operation, requests[operation](rows), EncodeReply, deadline
            )
            for operation, rows in groups.items()
            if rows
        }
        latents: list[Any] = [None] * len(images)
        errors: list[Any] = [None] * len(images)
        refused: list[str | None] = [None] * len(images)
        for operation, encoding in pending.items():
            try:
                reply: EncodeReply = encoding.result()
            except RemoteError as exc:  # a frame the encoder could not decode: which one
                raise FrameRefused.of(exc, groups[operation]) from None
            for k, i in enumerate(groups[operation]):
                latents[i] = reply.latents.numpy()[k]
                errors[i] = None if reply.errors is None else reply.errors.numpy()[k]
                refused[i] = None if reply.refused is None else reply.refused[k]
        known = None if any(e is None for e in errors) else WireArray.of(np.stack(errors))
        return np.stack(latents), known, refused, list(pending.values())

    def plan_with_reason(
        self,
        start: Image,
        goal: Image,
        max_plans: int = 8,
        include_images: bool = True,
        deadline: float | None = None,
        expect_node: int | None = None,
        avoid_steps: Sequence[tuple[int, int]] = (),
    ) -> PlanOutcome:
        """Plans from start to goal; every call shares one deadline (`time.monotonic()`), so a
        hang anywhere costs the caller that budget once, not once per call after slow ones.
        `expect_node`, `avoid_steps`: what a closed loop learned so far (PathsRequest)."""
        deadline = deadline or self.deadline()
        (z_start, z_goal), errors, refused, calls = self._encode([start, goal], deadline)
        search = PathsRequest(
            task=self.task_name,
            z_start=WireArray.of(z_start),
            z_goal=WireArray.of(z_goal),
            max_plans=max_plans,
            errors=errors,
            expect_node=expect_node,
            avoid_steps=list(avoid_steps),
        )
        searching = self._call("planner", "paths", search, PathsReply, deadline)
        found: PathsReply = searching.result()
        calls.append(searching)
        match = None
        if found.match is not None:
            match = {end: Match.from_json(m) for end, m in found.match.items()}
        for end, why in zip(("start", "goal"), refused, strict=True):
            if why is not None:  # not registered: not known, whatever its latent's match
                if match is not None:
                    match[end] = dataclasses.replace(match[end], known=False)
                return PlanOutcome(
                    [], f"the {end} image is not known: {why}", timings(calls), match
                )
        if not found.paths:
            return PlanOutcome([], found.reason, timings(calls), match)
        node_latents = found.node_latents.numpy()
        latents = dict(zip(found.node_ids, node_latents, strict=True))
        steps = list(dict.fromkeys((a, b) for p in found.paths for a, b in itertools.pairwise(p)))
        proposing = decoding = None
        if steps:
            propose = ProposeRequest(
                task=self.task_name,
                z_from=WireArray.of(np.stack([latents[a] for a, _ in steps])),
                z_to=WireArray.of(np.stack([latents[b] for _, b in steps])),
            )
            proposing = self._call("apn", "propose", propose, ProposeReply, deadline)
            calls.append(proposing)
        images: dict[int, np.ndarray] = {}
        missing: list[tuple[int, tuple[str, bytes]]] = []
        if include_images:
            for node, latent in zip(found.node_ids, node_latents, strict=True):
                key = (found.model_id, latent.tobytes())
                image = self.node_images.get(key)
                if image is None:
                    missing.append((node, key))
                else:
                    images[node] = image
        if missing:
            decode = DecodeRequest(
                task=self.task_name,
                latents=WireArray.of(np.stack([latents[node] for node, _ in missing])),
            )
            decoding = self._call("encoder", "decode", decode, DecodeReply, deadline)
            calls.append(decoding)
        proposed: dict[tuple[int, int], tuple[Any, float]] = {}
        if proposing is not None:
            reply: ProposeReply = proposing.result()
            for step, action, confidence in zip(
                steps, reply.actions, reply.confidences, strict=True
            ):
                parsed = None if action is None else self.task.parse_action(action)
                proposed[step] = (parsed, confidence)
        if decoding is not None:
            decoded: DecodeReply = decoding.result()
            for (node, key), image in zip(missing, decoded.images.numpy(), strict=True):
                image = image.copy()  # a row of the reply would keep the whole reply alive
                image.setflags(write=False)
                if decoded.model_id == found.model_id:  # not while models are being rolled out
                    self.node_images.put(key, image)
                images[node] = image
        plans = []
        for path, supports in zip(found.paths, found.supports, strict=True):
            pairs = [proposed[(a, b)] for a, b in itertools.pairwise(path)]
            if any(action is None for action, _ in pairs):
                continue  # the APN saw no action between two nodes: not a plan a robot can run
            plans.append(
                VisualActionPlan(
                    nodes=path,
                    images=[images[n] for n in path] if include_images else [],
                    actions=[action for action, _ in pairs],
                    confidences=[confidence for _, confidence in pairs],
                    supports=supports,
                )
            )
        reason = None if plans else "the APN proposed no action for a step of every path"
        return PlanOutcome(plans, reason, timings(calls), match)

    def plan(
        self,
        start: Image,
        goal: Image,
        max_plans: int = 8,
        include_images: bool = False,
        expect: int | None = None,
        avoid: Sequence[tuple[int, int]] = (),
    ) -> list[VisualActionPlan]:
        """The closed loop's Planner protocol: plans only, no decoded images unless asked;
        UnknownImageError when the planner refused an end. A camera's frames (pixels of
        another size than the model's) cross the bus compressed."""
        size = self.image_size()
        start, goal = (as_sent(image, size) or image for image in (start, goal))
        outcome = self.plan_with_reason(
            start, goal, max_plans, include_images, expect_node=expect, avoid_steps=avoid
        )
        end = None if outcome.match is None else refused_end(outcome.match)
        if end is not None and outcome.match is not None:
            raise UnknownImageError(end, outcome.reason or f"the {end} is not known", outcome.match)
        return outcome.plans

    def run(self, request: RunRequest, deadline_s: float) -> RunReply:
        """A closed-loop episode in a sim instance; it plans through this same network."""
        deadline = time.monotonic() + deadline_s
        return self._call("sim", "run", request, RunReply, deadline).result()


def as_sent(image: Image, size: int) -> bytes | None:
    """A frame's bytes as they cross the bus (pixels of another size than the model's
    compressed first); None for pixels at the model's `size`, which go as they are."""
    if isinstance(image, bytes):
        return image
    return None if image.shape[:2] == (size, size) else encode_frame(image)


def timings(calls: list[PendingCall]) -> list[CallTiming]:
    return [pending.timing for pending in calls if pending.timing is not None]
