"""The REST (and `lsr/api/plan`) request and response bodies, in one place."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from shared.appearance import APPEARANCES, LEVELS
from shared.bus import ROBOT_ID_PATTERN
from shared.messages import MAX_AVOID, MAX_PLANS, NodeId
from shared.tasks import DEFAULT_TASK, known_tasks


class Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class TaskRequest(Strict):
    task: str = Field(examples=[DEFAULT_TASK])

    @field_validator("task")
    @classmethod
    def _known_task(cls, task: str) -> str:
        if task not in known_tasks():
            raise ValueError(f"unknown task {task!r}; known tasks are {known_tasks()}")
        return task


APPEARANCE_DESCRIPTION = (
    "how the simulated camera sees: clean (a fixed rendering), camera (lights, camera pose, "
    "table, white balance, exposure, noise and JPEG varied as a real camera would) or shifted "
    "(every camera range doubled: for testing generalisation only); default: the appearance "
    "of the served model's training data"
)


class AppearanceRequest(Strict):
    appearance: str | None = Field(None, description=APPEARANCE_DESCRIPTION, examples=list(LEVELS))

    @field_validator("appearance")
    @classmethod
    def _known_level(cls, appearance: str | None) -> str | None:
        if appearance is not None and appearance not in APPEARANCES:
            raise ValueError(
                f"unknown appearance level {appearance!r}; known levels are {', '.join(LEVELS)}"
            )
        return appearance


class Endpoint(Strict):
    """A start or goal: a PNG/JPEG image (base64) or a task state, exactly one of them."""

    image: str | None = Field(None, description="PNG or JPEG, base64 (a data: URL prefix is ok)")
    state: dict[str, Any] | None = Field(None, examples=[{"stacks": [["red"], [], []]}])

    @model_validator(mode="after")
    def _exactly_one(self) -> Endpoint:
        if (self.image is None) == (self.state is None):
            raise ValueError("give exactly one of 'image' and 'state'")
        return self


class ExperienceTuple(Strict):
    """One executed action as the robot saw it; `action` null for a second look at a scene
    nothing changed (or an action that changed nothing)."""

    before: str = Field(description="PNG or JPEG, base64: what the robot saw before acting")
    action: dict[str, Any] | None = Field(description="the action executed, as in a plan")
    after: str = Field(description="PNG or JPEG, base64: what it saw after")


class ExperienceRequest(TaskRequest):
    tuples: list[ExperienceTuple] = Field(min_length=1, max_length=64)


class ExperienceResponse(BaseModel):
    recorded: int = Field(description="tuples recorded from this report")
    total: int = Field(description="tuples recorded for the task so far")


class StateEndpoint(Strict):
    state: dict[str, Any]


class PlanRequest(TaskRequest):
    start: Endpoint
    goal: Endpoint
    max_plans: int = Field(8, ge=1, le=MAX_PLANS)
    robot_id: str | None = Field(None, pattern=ROBOT_ID_PATTERN)
    include_images: bool = True
    expect_node: int | None = Field(
        None,
        ge=0,
        description="a robot re-planning after a step: the node that step was meant to reach "
        "(its plan's nodes[1]). The plans start there where the start image is known there "
        "too, so that a state the roadmap holds in several nodes is not re-planned from each "
        "in turn; ignored otherwise",
    )
    avoid_steps: list[tuple[NodeId, NodeId]] = Field(
        default_factory=list,
        max_length=MAX_AVOID,
        description="a robot re-planning after steps whose action led elsewhere: those steps "
        "[from node, to node] (a plan's nodes[0] and nodes[1]). No plan takes one of them where "
        "another plan exists, so that one wrong action is not repeated all task long; steps "
        "of nodes the roadmap does not have are ignored",
    )


class Plan(BaseModel):
    images: list[str] = Field(description="PNG base64, start to goal; empty without images")
    actions: list[dict[str, Any]]
    nodes: list[int]
    confidences: list[float] = Field(description="the APN's confidence in each action")
    confidence: float = Field(
        description="the product of the actions' confidences: how sure the APN is of the "
        "actions, not whether the nodes show the right states (docs/serving/knowing.md, "
        "'Plan confidence')"
    )
    supports: list[int] = Field(description="the training action pairs behind each step")
    support: float = Field(
        description="how well the training data backs every step: the product over steps of "
        "(w + 1) / (w + 2) for a step seen w times; docs/serving/knowing.md, 'Plan "
        "confidence', says how often plans at each support were valid"
    )


class EndMatch(BaseModel):
    known: bool
    score: float = Field(
        description="the largest of the image's latent distance to the nearest roadmap node "
        "and its reconstruction errors, each over the model's calibrated threshold: known while "
        "at most 1"
    )
    node: int | None = Field(description="the nearest roadmap node")


class PlanMatch(BaseModel):
    start: EndMatch
    goal: EndMatch


class PlanResponse(BaseModel):
    plan_id: str
    plans: list[Plan]
    reason: str | None = Field(None, description="why there is no plan, when plans is empty")
    match: PlanMatch | None = Field(
        None, description="how well the model knows each end; an end not known gets no plan"
    )


class RenderRequest(TaskRequest, AppearanceRequest):
    state: dict[str, Any]
    seed: int = Field(0, ge=0, le=2**32 - 1)
    frame: bool = Field(
        False,
        description="the cell camera's whole frame, with the table's markers round the view, "
        "as a camera gives it (/plan registers it); false: the view in the table frame",
    )


class RenderResponse(BaseModel):
    image: str


class ExecuteRequest(TaskRequest, AppearanceRequest):
    start: StateEndpoint
    goal: Endpoint
    max_steps: int = Field(20, ge=1, le=100)
    max_plans: int = Field(8, ge=1, le=MAX_PLANS)
    seed: int = Field(0, ge=0, le=2**32 - 1)


class ExecuteStep(BaseModel):
    action: dict[str, Any]
    image: str = Field(description="PNG base64 observed after the action")


class ExecuteResponse(BaseModel):
    success: bool = Field(description="the final state shows the goal's view (interface.md)")
    reason: str = Field(
        description="goal, or why the run stopped: unknown_start (a scene the model does not "
        "know: nothing was done from it), unknown_goal, unreachable, max_steps, physics: ..."
    )
    detail: str | None = Field(None, description="the planner's words, where it refused")
    final_state: dict[str, Any] | None = Field(
        description="the simulator's state at the end; null when it reads as no valid state"
    )
    final_view: dict[str, Any] | None = Field(
        None,
        description="what a camera above shows of that state: the state itself unless parts "
        "of it are hidden (the T-shirt's sleeve under its folded side, named in 'hidden')",
    )
    steps: list[ExecuteStep]


class Instance(BaseModel):
    instance: str
    task: str
    model_id: str
    uptime_s: float
    roadmap_version: str | None = Field(
        None, description="planners: the roadmap version planned with (it grows while serving)"
    )


class ServiceHealth(BaseModel):
    status: Literal["ok", "unavailable"]
    instances: list[Instance]


class Health(BaseModel):
    status: Literal["ok", "unavailable", "inconsistent"]
    services: dict[str, ServiceHealth]
    detail: str | None = None
