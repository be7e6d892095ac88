"""The planner service: all shortest roadmap paths between the nodes nearest two latents."""

from __future__ import annotations

import json
import logging
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from services.planner.knowing import ERRORS, Calibration, load_calibration, place_ends
from services.planner.places import Places
from services.planner.roadmap import Roadmap
from services.planner.versions import current_version, version_dir
from services.runtime import ServiceContext
from shared.bus import Handler
from shared.checkpoint import MANIFEST, CheckpointError, verify
from shared.messages import GraphReply, GraphRequest, PathsReply, PathsRequest, WireArray, unpack
from shared.plans import UnknownImageError
from shared.validation import FieldError, check_latents, check_task

log = logging.getLogger(__name__)
RELOAD_S = 1.0  # how often a planner looks for a new roadmap version


def node_labels(folder: Path, nodes: int) -> tuple[list[Any], list[float]] | None:
    """Each node's majority true state and purity from `labels.json`, when the builder wrote
    one that fits this roadmap; None otherwise (a model without states knows none)."""
    try:
        labels = json.loads((folder / "labels.json").read_text())
        by_node = {int(label["node"]): label for label in labels}
        if sorted(by_node) != list(range(nodes)):
            raise ValueError(f"labels for {len(by_node)} nodes, the roadmap has {nodes}")
        return (
            [by_node[i]["state"] for i in range(nodes)],
            [float(by_node[i]["purity"]) for i in range(nodes)],
        )
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        log.warning("%s/labels.json ignored: %s", folder, exc)
        return None


@dataclass(frozen=True)
class Served:
    """One roadmap version with what plans with it; replaced whole, never changed."""

    version: str
    roadmap: Roadmap
    calibration: Calibration
    labels: tuple[list[Any], list[float]] | None
    places: Places | None  # None for a model kept without its members

    @classmethod
    def load(cls, model_dir: Path, require_sealed: bool = False, check: bool = True) -> Served:
        """The current version; `check` its seal (the service start checked the first)."""
        version = current_version(model_dir)
        folder = version_dir(model_dir, version)
        if check and not verify(folder):
            if require_sealed:
                raise CheckpointError(f"{folder}: not sealed (no {MANIFEST}); not taken")
            log.warning("%s: not sealed: served unverified", folder)
        roadmap = Roadmap.load(folder)
        labels = node_labels(folder, roadmap.num_nodes)
        calibration = load_calibration(folder, roadmap)
        return cls(version, roadmap, calibration, labels, Places.load(folder, roadmap))


def watch_versions(
    model_dir: Path, served: list[Served], context: ServiceContext, every_s: float = RELOAD_S
) -> threading.Thread:
    """Take a new current version when `lsr roadmap grow` publishes one: loaded beside the
    old, then swapped in one assignment, so no request fails or sees half of each. A version
    that does not load is logged and the old one kept."""

    def run() -> None:
        failed = None  # the version that would not load, said once
        while not context.stopping.wait(every_s):
            version = None
            try:
                version = current_version(model_dir)
                if version in (served[0].version, failed):
                    continue
                fresh = Served.load(model_dir, context.settings.require_sealed_model)
            except (OSError, ValueError) as exc:
                failed = version
                log.warning("roadmap version %s not taken: %s", version, exc)
                continue
            served[0] = fresh
            context.status["roadmap_version"] = fresh.version
            log.info("planning with roadmap %s", fresh.version)

    thread = threading.Thread(target=run, name="roadmap-versions", daemon=True)
    thread.start()
    return thread


def setup(context: ServiceContext) -> dict[str, Handler]:
    served = [Served.load(context.model.directory, check=False)]  # ModelInfo.read checked it
    context.status["roadmap_version"] = served[0].version
    watch_versions(context.model.directory, served, context, every_s=RELOAD_S)
    dim, task = context.model.latent_dim, context.model.task

    def paths(payload: bytes) -> PathsReply:
        now = served[0]  # one version for the whole request
        roadmap, calibration = now.roadmap, now.calibration
        request = unpack(payload, PathsRequest)
        check_task(request.task, task)
        z_start = check_latents("z_start", request.z_start, dim, ndim=1)
        z_goal = check_latents("z_goal", request.z_goal, dim, ndim=1)
        if request.errors is None:
            raise FieldError("errors", "both images' reconstruction errors are needed")
        errors = request.errors.numpy().astype(np.float64)
        if errors.shape != (2, len(ERRORS)) or not np.isfinite(errors).all() or (errors < 0).any():
            raise FieldError(
                "errors",
                f"must be 2 x {len(ERRORS)} finite, non-negative numbers ({', '.join(ERRORS)})",
            )
        try:
            matched, start, goal = place_ends(
                roadmap, calibration, z_start, z_goal, errors, request.expect_node, now.places
            )
        except UnknownImageError as refused:
            return PathsReply(
                paths=[],
                supports=[],
                node_ids=[],
                node_latents=WireArray.of(np.zeros((0, dim), np.float32)),
                model_id=context.model.model_id,
                reason=refused.reason,
                match={end: m.to_json() for end, m in refused.match.items()},
                roadmap_version=now.version,
            )
        # like expect_node, a hint: steps of nodes another roadmap version had are ignored
        avoid = [step for step in request.avoid_steps if max(step) < roadmap.num_nodes]
        found = roadmap.shortest_paths(start, goal, request.max_plans, avoid)
        node_ids = sorted({n for path in found for n in path})
        return PathsReply(
            paths=found,
            supports=[roadmap.supports(p) for p in found],
            node_ids=node_ids,
            node_latents=WireArray.of(roadmap.nodes[node_ids].astype(np.float32).reshape(-1, dim)),
            model_id=context.model.model_id,
            reason=None if found else "start and goal are not connected in the roadmap",
            match={end: m.to_json() for end, m in matched.items()},
            roadmap_version=now.version,
        )

    def graph(payload: bytes) -> GraphReply:
        check_task(unpack(payload, GraphRequest).task, task)
        now = served[0]
        roadmap, labels = now.roadmap, now.labels
        return GraphReply(
            node_latents=WireArray.of(roadmap.nodes.astype(np.float32).reshape(-1, dim)),
            edges=WireArray.of(roadmap.edges.astype(np.int64).reshape(-1, 2)),
            edge_weights=WireArray.of(roadmap.edge_weights.astype(np.int64)),
            twins=WireArray.of(roadmap.twins.astype(np.int64).reshape(-1, 2)),
            states=None if labels is None else labels[0],
            purity=None if labels is None else labels[1],
            model_id=context.model.model_id,
            roadmap_version=now.version,
        )

    return {"paths": paths, "graph": graph}
