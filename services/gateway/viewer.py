"""The plan viewer: a static page at `/` and the routes only pictures need.

Kept apart from the API routes of `app.py`, so that nothing here sits on the path of `/plan`:
- `GET /` and `/ui/*`: the page (static files, no build step, no library; open without an API
  key, as they hold no data: every call the page makes carries the key the user gives it);
- `GET /tasks/{task}/roadmap`: the roadmap graph (nodes with a 2-D layout and, where the model
  knows them, their states; weighted edges), asked of the planner;
- `GET /tasks/{task}/roadmap/nodes/{node}.png`: a node's decoded image, asked of the encoder;
- `POST /action-pixels`: where actions act in the images (pick and release marks
  drawn by the page), asked of the sim's world;
- `POST /execute/stream`: `/execute` as server-sent events, one per executed step as the sim
  publishes it (`RunRequest.progress`), then the outcome.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import zenoh
from fastapi import FastAPI, HTTPException, Request
from fastapi import Path as PathParam
from fastapi.responses import FileResponse, Response, StreamingResponse
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, Field
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import shortest_path

from services.gateway.errors import error_body
from services.gateway.planning import Gateway
from services.gateway.schemas import ExecuteRequest, TaskRequest
from shared.bus import call, progress_key
from shared.graphs import twin_groups
from shared.images import encode_png, png_b64
from shared.lru import LruCache
from shared.messages import (
    DecodeReply,
    DecodeRequest,
    GraphReply,
    GraphRequest,
    PixelsReply,
    PixelsRequest,
    RunReply,
    RunRequest,
    RunStep,
    WireArray,
    unpack,
)
from shared.tasks import get_task
from shared.tasks.base import TaskError
from shared.validation import FieldError

log = logging.getLogger(__name__)
STATIC = Path(__file__).resolve().parent / "static"
UI_PREFIX = "/ui/"


# bodies -------------------------------------------------------------------------------------
class PixelsBody(TaskRequest):
    actions: list[dict[str, Any]] = Field(min_length=1, max_length=256)


class Mark(BaseModel):
    pick: tuple[float, float] = Field(description="x, y in pixels of the model's image")
    release: tuple[float, float]


class PixelsResponse(BaseModel):
    image_size: int
    marks: list[Mark]


class RoadmapNode(BaseModel):
    id: int
    x: float = Field(description="layout position in [0, 1]")
    y: float
    state: dict[str, Any] | None = Field(
        description="the most common state of the node's majority view, if known"
    )
    view: dict[str, Any] | None = Field(
        None,
        description="what a camera above shows of it: the state, less any part it hides "
        "(named in 'hidden', drawn as unknown)",
    )
    purity: float | None
    group: int = Field(description="its twin group: the smallest id of the nodes of one state")


def node_views(task: str, states: list[dict[str, Any] | None]) -> list[dict[str, Any] | None]:
    """Each labelled node's view (Task.view_to_json); None where a node or task has no state."""
    try:
        known = get_task(task)
        return [None if s is None else known.view_to_json(known.parse_state(s)) for s in states]
    except TaskError:  # a task known only from its data: no states to view
        return [None] * len(states)


class RoadmapGraph(BaseModel):
    task: str
    model_id: str
    roadmap_version: str | None = Field(None, description="which version of a growing roadmap")
    layout: str = Field(description="how x and y were found")
    nodes: list[RoadmapNode]
    edges: list[tuple[int, int, int]] = Field(description="node, node, supporting action pairs")
    twins: list[tuple[int, int]] = Field(
        description="nodes that experience showed to be one state: a path steps between their "
        "groups along any edge joining them"
    )


# the layout ---------------------------------------------------------------------------------
def graph_layout(nodes: int, edges: np.ndarray) -> np.ndarray:
    """(K, 2) positions in [0, 1]: classical MDS of the hop distances between nodes.

    Hops, not latent distances: the picture is of the graph the planner searches, so that a
    plan's path is short on screen exactly when it is short for the planner. Nodes in other
    components sit one hop beyond the farthest pair; the result is deterministic (eigenvectors'
    signs fixed by their largest entry).
    """
    if nodes == 0:
        return np.zeros((0, 2))
    if nodes == 1:
        return np.full((1, 2), 0.5)
    rows = np.concatenate([edges[:, 0], edges[:, 1]]) if len(edges) else np.zeros(0, int)
    cols = np.concatenate([edges[:, 1], edges[:, 0]]) if len(edges) else np.zeros(0, int)
    adjacency = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(nodes, nodes)).tocsr()
    hops = shortest_path(adjacency, unweighted=True, directed=False)
    finite = hops[np.isfinite(hops)]
    hops[~np.isfinite(hops)] = (finite.max() if finite.size else 0) + 1
    centred = np.eye(nodes) - 1.0 / nodes
    gram = -0.5 * centred @ (hops**2) @ centred
    values, vectors = np.linalg.eigh(gram)
    top = vectors[:, ::-1][:, :2] * np.sqrt(np.maximum(values[::-1][:2], 0))
    for k in range(2):
        if top[np.argmax(np.abs(top[:, k])), k] < 0:
            top[:, k] = -top[:, k]
    low, high = top.min(axis=0), top.max(axis=0)
    span = np.where(high - low > 0, high - low, 1.0)
    return 0.05 + 0.9 * (top - low) / span


# the routes ---------------------------------------------------------------------------------
class Viewer:
    """What the page's routes need beyond `Gateway`: the graph and node images, cached by model."""

    def __init__(self, gateway: Gateway) -> None:
        self.gateway = gateway
        self._graphs: dict[str, tuple[RoadmapGraph, np.ndarray]] = {}  # task -> graph, latents
        self._lock = threading.Lock()
        self.node_pngs: LruCache[tuple[str, str, bytes], bytes] = LruCache()

    def _call(self, task: str, service: str, operation: str, request: BaseModel, kind: type) -> Any:
        client = self.gateway.client(task)
        deadline_s = self.gateway.settings.deadline_s
        pending = call(
            self.gateway.session,
            service,
            task,
            operation,
            request,
            kind,
            deadline_s,
            client.replicas,
        )
        return pending.result()

    def graph(self, task: str) -> tuple[RoadmapGraph, np.ndarray]:
        """The roadmap now served for `task`; the layout is computed once per model."""
        reply: GraphReply = self._call(
            task, "planner", "graph", GraphRequest(task=task), GraphReply
        )
        with self._lock:
            cached = self._graphs.get(task)
        served = (reply.model_id, reply.roadmap_version)
        if cached is not None and (cached[0].model_id, cached[0].roadmap_version) == served:
            return cached
        latents = reply.node_latents.numpy()
        edges, weights = reply.edges.numpy(), reply.edge_weights.numpy()
        twins = np.zeros((0, 2), np.int64) if reply.twins is None else reply.twins.numpy()
        positions = graph_layout(len(latents), np.concatenate([edges, twins]))
        groups = twin_groups(len(latents), twins)
        states = reply.states or [None] * len(latents)
        views = node_views(task, states)
        purity = reply.purity or [None] * len(latents)
        graph = RoadmapGraph(
            task=task,
            model_id=reply.model_id,
            roadmap_version=reply.roadmap_version,
            layout="classical MDS of hop distances",
            nodes=[
                RoadmapNode(
                    id=i,
                    x=float(x),
                    y=float(y),
                    state=states[i],
                    view=views[i],
                    purity=purity[i],
                    group=int(groups[i]),
                )
                for i, (x, y) in enumerate(positions)
            ],
            edges=[(int(a), int(b), int(w)) for (a, b), w in zip(edges, weights, strict=True)],
            twins=[(int(a), int(b)) for a, b in twins],
        )
        with self._lock:
            self._graphs[task] = (graph, latents)
        return graph, latents

    def node_png(self, task: str, node: int) -> bytes:
        graph, latents = self.graph(task)
        if not 0 <= node < len(latents):
            raise HTTPException(404, f"node {node} is not in the roadmap (it has {len(latents)})")
        key = (task, graph.model_id, latents[node].tobytes())  # ids change as roadmaps grow
        cached = self.node_pngs.get(key)
        if cached is not None:
            return cached
        request = DecodeRequest(task=task, latents=WireArray.of(latents[node : node + 1]))
        reply: DecodeReply = self._call(task, "encoder", "decode", request, DecodeReply)
        png = encode_png(reply.images.numpy()[0])
        if reply.model_id == graph.model_id:  # not while models are being rolled out
            self.node_pngs.put(key, png)
        return png

    def pixels(self, body: PixelsBody) -> PixelsResponse:
        logic = get_task(self.gateway.served(body.task))
        for i, action in enumerate(body.actions):
            try:
                logic.parse_action(action)
            except TaskError as exc:
                raise FieldError(f"actions.{i}", str(exc)) from None
        request = PixelsRequest(task=body.task, actions=body.actions)
        reply: PixelsReply = self._call(body.task, "sim", "pixels", request, PixelsReply)
        marks = [
            Mark(pick=(float(a), float(b)), release=(float(c), float(d)))
            for a, b, c, d in reply.pixels.numpy()
        ]
        return PixelsResponse(image_size=reply.image_size, marks=marks)

    def execute_events(self, body: ExecuteRequest) -> Iterator[str]:
        """Server-sent events of one episode: `step` per action, then `done` (or `error`).

        The input is checked now, before any event, so that bad input gets a 4xx reply."""
        run_id = uuid.uuid4().hex
        return self._episode(body, self.gateway.run_request(body, run_id), run_id)

    def _episode(self, body: ExecuteRequest, run: RunRequest, run_id: str) -> Iterator[str]:
        events: queue.Queue[tuple[str, Any]] = queue.Queue()

        def heard(sample: zenoh.Sample) -> None:
            try:
                events.put(("step", unpack(sample.payload.to_bytes(), RunStep)))
            except Exception:  # unreadable: the final reply still carries the step
                return

        settings = self.gateway.settings
        deadline_s = settings.deadline_s + settings.execute_step_s * body.max_steps

        def run_episode() -> None:
            try:
                events.put(("done", self.gateway.client(body.task).run(run, deadline_s)))
            except Exception as exc:
                events.put(("failed", exc))

        # Declared before the query is sent (one session, in order), so no step goes unheard.
        subscriber = self.gateway.session.declare_subscriber(progress_key(body.task, run_id), heard)
        try:
            threading.Thread(target=run_episode, name="execute-stream", daemon=True).start()
            sent = 0
            yield sse("started", {})
            while True:
                kind, item = events.get()
                if kind == "step" and item.step == sent + 1:
                    sent += 1
                    yield sse("step", step_json(item.step, item.action, item.state, item.image))
                elif kind == "done":
                    reply: RunReply = item
                    images = reply.images.numpy()
                    for i in range(sent, len(reply.actions)):  # any the bus has not brought
                        yield sse("step", step_json(i + 1, reply.actions[i], None, images[i]))
                    outcome = {
                        "success": reply.success,
                        "reason": reply.reason,
                        "detail": reply.detail,
                        "final_state": reply.final_state,
                        "final_view": reply.final_view,
                        "steps": len(reply.actions),
                    }
                    yield sse("done", outcome)
                    return
                elif kind == "failed":
                    known = error_body(item)
                    if known is None:
                        log.error("/execute/stream failed", exc_info=item)
                    status, detail = known or (500, "internal error")
                    yield sse("error", {"status": status, "detail": detail})
                    return
        finally:
            subscriber.undeclare()


def step_json(step: int, action: dict[str, Any], state: Any, image: Any) -> dict[str, Any]:
    if isinstance(image, WireArray):
        image = image.numpy()
    return {"step": step, "action": action, "state": state, "image": png_b64(np.asarray(image))}


def sse(event: str, data: Any) -> str:
    return f"event: {event}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n"


def add_viewer(app: FastAPI) -> None:
    """The page and its routes; `app.state.gateway` must exist when they are called."""

    def viewer(request: Request) -> Viewer:
        state = request.app.state
        if getattr(state, "viewer", None) is None or state.viewer.gateway is not state.gateway:
            state.viewer = Viewer(state.gateway)
        return state.viewer

    @app.get("/", include_in_schema=False)
    def page() -> FileResponse:
        return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-cache"})

    app.mount(UI_PREFIX.rstrip("/"), StaticFiles(directory=STATIC), name="ui")

    @app.get("/tasks/{task}/roadmap", response_model=RoadmapGraph)
    def roadmap(task: str, request: Request) -> RoadmapGraph:
        """The roadmap graph of `task`'s model, laid out in 2-D, for the page's picture."""
        return viewer(request).graph(task)[0]

    @app.get("/tasks/{task}/roadmap/nodes/{node}.png", response_class=Response)
    def roadmap_node(
        task: str, request: Request, node: int = PathParam(ge=0, le=2**31 - 1)
    ) -> Response:
        """A roadmap node's decoded image."""
        png = viewer(request).node_png(task, node)
        return Response(png, media_type="image/png", headers={"Cache-Control": "private"})

    @app.post("/action-pixels")
    def action_pixels(body: PixelsBody, request: Request) -> PixelsResponse:
        """Where each action's pick and release appear in the model's images."""
        return viewer(request).pixels(body)

    @app.post(
        "/execute/stream",
        response_class=StreamingResponse,
        responses={200: {"content": {"text/event-stream": {}}}},
    )
    def execute_stream(body: ExecuteRequest, request: Request) -> StreamingResponse:
        """`/execute` as server-sent events: `started`, a `step` per executed action (its
        action, the state the sim reads, the observed image), then `done` or `error`."""
        events = viewer(request).execute_events(body)
        return StreamingResponse(
            events,
            media_type="text/event-stream",
            headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
        )
