"""The planner service: all shortest roadmap paths between the nodes nearest two latents."""

from __future__ import annotations

import numpy as np

from services.planner.roadmap import Roadmap
from services.runtime import ServiceContext
from shared.bus import Handler
from shared.messages import PathsReply, PathsRequest, WireArray, unpack
from shared.validation import check_latents, check_task


def roadmap_paths(
    roadmap: Roadmap, z_start: np.ndarray, z_goal: np.ndarray, max_paths: int
) -> list[list[int]]:
    start, goal = (int(n) for n in roadmap.nearest_node(np.stack([z_start, z_goal])))
    return roadmap.shortest_paths(start, goal, max_paths=max_paths)


def setup(context: ServiceContext) -> dict[str, Handler]:
    roadmap = Roadmap.load(context.model.directory / "roadmap")
    dim, task = context.model.latent_dim, context.model.task

    def paths(payload: bytes) -> PathsReply:
        request = unpack(payload, PathsRequest)
        check_task(request.task, task)
        z_start = check_latents("z_start", request.z_start, dim, ndim=1)
        z_goal = check_latents("z_goal", request.z_goal, dim, ndim=1)
        found = roadmap_paths(roadmap, z_start, z_goal, request.max_plans)
        node_ids = sorted({n for path in found for n in path})
        return PathsReply(
            paths=found,
            node_ids=node_ids,
            node_latents=WireArray.of(roadmap.nodes[node_ids].astype(np.float32).reshape(-1, dim)),
            model_id=context.model.model_id,
            reason=None if found else "start and goal are not connected in the roadmap",
        )

    return {"paths": paths}
