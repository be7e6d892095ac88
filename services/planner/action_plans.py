"""Visual action plans: roadmap paths with decoded images and the APN's action for each step."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from services.apn.model import APN
from services.apn.train import load_apn, propose
from services.encoder.checkpoint import load_vae, read_vae_config
from services.planner.build import load_labels
from services.planner.evaluate import TransitionChecker, action_leads
from services.planner.knowing import load_calibration
from services.planner.places import Places
from services.planner.plan import VisualPlanner
from services.planner.roadmap import Roadmap
from services.planner.versions import roadmap_dir
from services.runtime import declare_model_task
from shared.plans import VisualActionPlan
from shared.tasks import get_task
from shared.tasks.base import Task


class ActionPlanner:
    """Encoder + roadmap + APN in one process: images in, visual action plans out."""

    def __init__(self, task: Task, planner: VisualPlanner, apn: APN) -> None:
        self.task = task
        self.planner = planner
        self.apn = apn

    @classmethod
    def from_model_dir(cls, model_dir: Path | str) -> ActionPlanner:
        """A model folder with vae/, roadmap/ and apn/ side by side."""
        model_dir = Path(model_dir)
        vae, config = load_vae(model_dir / "vae")
        apn, _ = load_apn(model_dir / "apn")
        folder = roadmap_dir(model_dir)
        roadmap = Roadmap.load(folder)
        calibration = load_calibration(folder, roadmap)
        declare_model_task(config)
        planner = VisualPlanner(vae, roadmap, calibration, Places.load(folder, roadmap))
        return cls(get_task(config["dataset"]["task"]), planner, apn)

    @property
    def image_size(self) -> int:
        return self.planner.vae.config.image_size

    def encode(self, image: np.ndarray) -> np.ndarray:
        return self.planner.encode(image[None])[0]

    def plan(
        self,
        start: np.ndarray,
        goal: np.ndarray,
        max_plans: int = 8,
        expect: int | None = None,
        avoid: Sequence[tuple[int, int]] = (),
    ) -> list[VisualActionPlan]:
        """Plans from a start image to a goal image, in the roadmap's deterministic order;
        UnknownImageError when an end is unlike anything the model knows."""
        z, errors = self.planner.look(np.stack([start, goal]))
        return self.plan_latent(z[0], z[1], max_plans, errors, expect, avoid)

    def plan_latent(
        self,
        z_start: np.ndarray,
        z_goal: np.ndarray,
        max_plans: int = 8,
        errors: np.ndarray | None = None,
        expect: int | None = None,
        avoid: Sequence[tuple[int, int]] = (),
    ) -> list[VisualActionPlan]:
        plans = []
        found = self.planner.plan_latent(z_start, z_goal, max_plans, errors, expect, avoid)
        for latent_plan in found:
            z = latent_plan.latents
            arrays, confidences = propose(self.apn, z[:-1], z[1:]) if len(z) > 1 else ([], [])
            plans.append(
                VisualActionPlan(
                    nodes=latent_plan.nodes,
                    images=self.planner.node_images(latent_plan.nodes),
                    actions=[self.task.array_to_action(a) for a in arrays],
                    confidences=[float(c) for c in confidences],
                    supports=self.planner.roadmap.supports(latent_plan.nodes),
                )
            )
        return plans

    def skip_first(self, plan: VisualActionPlan) -> VisualActionPlan:
        """`plan` with its first two steps as one: the APN's action from the first node straight
        to the third. The roadmap has no edge between them (else the path were shorter), so
        executing it shows whether the data only missed that move (issue 22: shortcuts)."""
        if len(plan.nodes) < 3:
            raise ValueError("a plan needs two steps to skip one")
        z = self.planner.roadmap.nodes[[plan.nodes[0], plan.nodes[2]]].astype(np.float32)
        arrays, confidences = propose(self.apn, z[:1], z[1:])
        return VisualActionPlan(
            nodes=[plan.nodes[0], *plan.nodes[2:]],
            images=[plan.images[0], *plan.images[2:]] if plan.images else [],
            actions=[self.task.array_to_action(arrays[0]), *plan.actions[2:]],
            confidences=[float(confidences[0]), *plan.confidences[2:]],
            supports=[0, *plan.supports[2:]],
        )


def edge_actions(
    task: Task, roadmap: Roadmap, apn: APN, node_states: list[Any], show: int = 5
) -> dict[str, Any]:
    """The APN's action on every roadmap edge, both ways, applied by the task's rules to the
    first node's state (or one that looks like it): does it give the second node's view? Plans
    are chains of these edges (between twin groups, by their first nodes) and the APN sees only
    the nodes' latents, so these are the actions a closed loop can execute."""
    edges = [(int(a), int(b)) for a, b in roadmap.group_edges]
    edges += [(b, a) for a, b in edges]
    if not edges:
        return {"edges": 0, "right": 0, "wrong": []}
    ids = np.array(edges)
    z = roadmap.nodes.astype(np.float32)
    arrays, _ = propose(apn, z[ids[:, 0]], z[ids[:, 1]])
    checker = TransitionChecker(task)
    wrong = []
    for (a, b), array in zip(edges, arrays, strict=True):
        action = task.array_to_action(array)
        if not action_leads(checker, node_states[a], action, node_states[b]):
            wrong.append(
                {
                    "from": task.state_to_json(node_states[a]),
                    "to": task.state_to_json(node_states[b]),
                    "action": None if action is None else task.action_to_json(action),
                }
            )
    return {"edges": len(edges), "right": len(edges) - len(wrong), "wrong": wrong[:show]}


def model_edge_actions(model_dir: Path | str, apn_dir: Path | str) -> dict[str, Any]:
    """edge_actions for a model folder (vae/ and roadmap/ with node labels) and an APN."""
    model_dir = Path(model_dir)  # the VAE is not needed: the APN reads the nodes' latents
    task = get_task(read_vae_config(model_dir / "vae")["dataset"]["task"])
    folder = roadmap_dir(model_dir)
    roadmap = Roadmap.load(folder)
    labels = load_labels(folder, task.name)
    states = [task.array_to_state(s) for s in labels.states]
    return edge_actions(task, roadmap, load_apn(apn_dir)[0], states)
