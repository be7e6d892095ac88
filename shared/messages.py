"""Messages between the services: typed, versioned, msgpack on the wire, arrays as raw bytes.

Every message carries `v` (the schema version). Arrays travel as little-endian bytes with their
shape and dtype, so a 64x64 image costs 12 KiB plus a few bytes of header, not a JSON list.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal, TypeVar, get_args

import msgpack
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

SCHEMA_VERSION = 1
MAX_PLANS = 64
MAX_AVOID = 64  # steps a closed loop asks to avoid: one per missed step, a task at most
NodeId = Annotated[int, Field(ge=0)]
WireDtype = Literal["|u1", "<f4", "<i8"]  # uint8 images, float32 latents, int64 ids
# Far beyond any real array, and small enough that numpy can always take the shape: a shape of
# huge dimensions and a zero one holds no bytes, so the byte count alone would let it through.
MAX_DIM = 2**31 - 1
MAX_ELEMENTS = 2**31  # the product of the nonzero dimensions


class MessageError(ValueError):
    """Bytes that are not a valid message of the expected kind; the message names the field,
    and so does `field` (dotted) where one is at fault."""

    def __init__(self, message: str, field: str | None = None) -> None:
        super().__init__(message)
        self.field = field


class WireArray(BaseModel):
    """An n-d array as little-endian bytes."""

    model_config = ConfigDict(frozen=True)

    shape: list[Annotated[int, Field(ge=0, le=MAX_DIM)]] = Field(max_length=8)
    dtype: WireDtype
    data: bytes

    @model_validator(mode="after")
    def _size_matches(self) -> WireArray:
        if math.prod(d for d in self.shape if d) > MAX_ELEMENTS:
            raise ValueError(f"shape {self.shape} has over {MAX_ELEMENTS} elements")
        expected = math.prod(self.shape) * np.dtype(self.dtype).itemsize  # exact, no overflow
        if len(self.data) != expected:
            raise ValueError(f"{len(self.data)} bytes for shape {self.shape} of {self.dtype}")
        return self

    @classmethod
    def of(cls, array: np.ndarray) -> WireArray:
        array = np.asarray(array)
        dtype = np.dtype(array.dtype).newbyteorder("<")
        if dtype.str not in get_args(WireDtype):
            raise TypeError(f"dtype {array.dtype} cannot go on the wire")
        return cls(shape=list(array.shape), dtype=dtype.str, data=array.astype(dtype).tobytes())

    def numpy(self) -> np.ndarray:
        return np.frombuffer(self.data, dtype=np.dtype(self.dtype)).reshape(self.shape)


class Message(BaseModel):
    model_config = ConfigDict(extra="forbid")

    v: int = SCHEMA_VERSION


class TaskMessage(Message):
    task: str


# encoder ------------------------------------------------------------------------------------
class EncodeRequest(TaskMessage):
    images: WireArray  # uint8 (N, S, S, 3): at the model's size, images in the table frame


class EncodeReply(Message):
    latents: WireArray  # float32 (N, D): the encoder means
    errors: WireArray | None = None  # float32 (N, 3): knowing.ERRORS of each image
    # per image, why its frame could not be registered (None: it was, or needed not be);
    # such an image is not known, whatever its latent says
    refused: list[str | None] | None = None


# A camera frame crosses the bus as the PNG or JPEG bytes a client sent (never as raw pixels:
# a 4096 px frame's are 50 MB); the encoder decodes it (a JPEG reduced, in the decoder) and
# registers it to the table frame (shared.registration.to_table_frame).
MAX_FRAME_BYTES = 32 * 2**20
Frame = Annotated[bytes, Field(min_length=1, max_length=MAX_FRAME_BYTES)]


class FramesRequest(TaskMessage):
    """Camera frames to encode (the `frames` operation, answered with an EncodeReply) or only
    to register (`register`, a RegisterReply): work of its own queue, apart from `encode`."""

    frames: list[Frame] = Field(min_length=1, max_length=8)


class RegisterReply(Message):
    images: WireArray  # uint8 (N, S, S, 3): in the table frame at the model's size
    refused: list[str | None] | None = None  # as EncodeReply's


class DecodeRequest(TaskMessage):
    latents: WireArray  # float32 (N, D)


class DecodeReply(Message):
    images: WireArray  # uint8 (N, H, W, 3)
    model_id: str | None = None  # the decoder's model: callers keep images only of their own


# planner ------------------------------------------------------------------------------------
class PathsRequest(TaskMessage):
    z_start: WireArray  # float32 (D,)
    z_goal: WireArray
    max_plans: int = Field(8, ge=1, le=MAX_PLANS)
    errors: WireArray | None = None  # float32 (2, 3): both images' EncodeReply.errors
    # the node a closed loop's last step was meant to reach (the last plan's nodes[1]): the
    # path starts there where the start image is known there too (knowing.keep_place)
    expect_node: int | None = Field(None, ge=0)
    # steps (from node, to node) whose action led elsewhere in this task: no path takes them
    # where another path exists (Roadmap.shortest_paths)
    avoid_steps: list[tuple[NodeId, NodeId]] = Field(default_factory=list, max_length=MAX_AVOID)


class PathsReply(Message):
    paths: list[list[int]]  # roadmap node ids, start to goal, all shortest paths (bounded)
    supports: list[list[int]]  # per path, the training action pairs behind each step
    node_ids: list[int]  # every node on some path, once
    node_latents: WireArray  # float32 (len(node_ids), D)
    model_id: str  # the planner's model: callers may keep node images decoded for it
    reason: str | None = None  # why `paths` is empty
    # {"start": {"known", "score", "node"}, "goal": {...}}: how well the model knows each end
    match: dict[str, dict[str, Any]] | None = None
    roadmap_version: str | None = None  # which version of the model's roadmap planned (v1, ...)


class GraphRequest(TaskMessage):
    """The whole roadmap, for pictures of it (the plan viewer); nothing plans with this."""


class GraphReply(Message):
    node_latents: WireArray  # float32 (K, D): node i is row i
    edges: WireArray  # int64 (E, 2), i < j
    edge_weights: WireArray  # int64 (E,)
    twins: WireArray | None = None  # int64 (T, 2), i < j: nodes experience showed to be one state
    states: list[Any] | None = None  # each node's majority true state, when the model knows it
    purity: list[float] | None = None  # the share of its members in that state
    model_id: str
    roadmap_version: str | None = None


# apn ----------------------------------------------------------------------------------------
class ProposeRequest(TaskMessage):
    z_from: WireArray  # float32 (M, D)
    z_to: WireArray


class ProposeReply(Message):
    actions: list[dict[str, Any] | None]  # the task's action JSON per pair
    confidences: list[float]


# sim ----------------------------------------------------------------------------------------
class RenderRequest(TaskMessage):
    states: list[Any] = Field(min_length=1, max_length=64)  # the task's state JSON
    seed: int = Field(0, ge=0, lt=2**63)
    appearance: str | None = None  # a level of shared.appearance; None: the model's training one
    frame: bool = False  # the cell camera's whole frame (markers round the view), not the view


class RenderReply(Message):
    images: WireArray


PROGRESS_ID_PATTERN = r"^[0-9a-f]{32}$"  # one key chunk, chosen by the caller (a uuid4 hex)


class RunRequest(TaskMessage):
    """A closed-loop episode in the sim's physics, planning through the other services.

    With `progress`, every executed step is also published as a `RunStep` on
    `shared.bus.progress_key(task, progress)` while the episode runs (for streaming clients).
    """

    start: Any  # state JSON
    goal_state: Any | None = None
    goal_image: Frame | None = None  # PNG or JPEG bytes, as the client sent them
    max_steps: int = Field(20, ge=1, le=200)
    max_plans: int = Field(8, ge=1, le=MAX_PLANS)
    seed: int = Field(0, ge=0, lt=2**63)
    progress: str | None = Field(None, pattern=PROGRESS_ID_PATTERN)
    appearance: str | None = None  # a level of shared.appearance; None: the model's training one


class RunStep(Message):
    """One executed action of a running episode, as it happens."""

    step: int  # 1 for the first action
    action: dict[str, Any]
    state: Any  # the state the sim reads after it
    image: WireArray  # uint8 (H, W, 3): what the camera sees after it


class PixelsRequest(TaskMessage):
    """Where actions act in the model's images (pick and release marks for pictures)."""

    actions: list[Any] = Field(min_length=1, max_length=256)  # the task's action JSON


class PixelsReply(Message):
    pixels: WireArray  # float32 (N, 4): pick x, y, release x, y in pixels (x right, y down)
    image_size: int


class RunReply(Message):
    success: bool
    reason: str
    detail: str | None = None  # the planner's words where it refused the scene
    final_state: Any
    actions: list[dict[str, Any]]
    final_view: Any = None  # what a camera above shows of it (Task.view_to_json)
    images: WireArray  # uint8 (steps, H, W, 3): observed after each action


# every service ------------------------------------------------------------------------------
class InfoReply(Message):
    service: str
    instance: str
    task: str
    model_id: str  # sha256 prefix of the VAE weights every service of one model shares
    image_size: int
    latent_dim: int
    pid: int
    uptime_s: float
    roadmap_version: str | None = None  # the planner's: grown roadmaps switch while serving


class CallBudget(Message):
    """Attached to every service query: how long its caller waits (queued longer: dropped)."""

    budget_ms: int = Field(ge=0)


class ReplyMeta(Message):
    """Attached to every service reply: who answered, and how long its handler took."""

    instance: str
    handler_ms: float


class ErrorReply(Message):
    code: Literal["bad_request", "unavailable", "internal"]
    message: str
    field: str | None = None  # the request field at fault, dotted; for unavailable: the service


M = TypeVar("M", bound=BaseModel)


def pack(message: BaseModel) -> bytes:
    return msgpack.packb(message.model_dump(mode="python"), use_bin_type=True)


def unpack(payload: bytes, kind: type[M]) -> M:
    """Bytes -> a `kind` message; MessageError names the version or field that is wrong.

    Errors are raised outside the except blocks: an exception raised inside one keeps the one it
    replaces, whose traceback holds the frames of this call and its callers (a query among them)
    in a cycle until the garbage collector runs.
    """
    problem = None
    try:
        obj = msgpack.unpackb(payload, raw=False)
    except Exception as exc:
        problem = f"not msgpack: {exc}"
    if problem is not None:
        raise MessageError(problem)
    if not isinstance(obj, dict):
        raise MessageError(f"{kind.__name__} must be a map, got {type(obj).__name__}")
    if obj.get("v") != SCHEMA_VERSION:
        raise MessageError(f"schema version {obj.get('v')!r} is not {SCHEMA_VERSION}")
    try:
        return kind.model_validate(obj)
    except ValidationError as exc:
        error = exc.errors()[0]
    field = ".".join(str(p) for p in error["loc"])
    raise MessageError(f"{kind.__name__}.{field}: {error['msg']}", field=field or None)
