"""Camera frames over a real router and gateway, with the services played by the test: a frame
crosses the bus as the client's bytes, and a flood of frames leaves light requests answered."""

from __future__ import annotations

import base64
import io
import time
from concurrent.futures import ThreadPoolExecutor

import httpx
import numpy as np
import pytest
from PIL import Image

from shared.bus import Batched, BusConfig, Server, close_quietly, open_session, service_key
from shared.messages import (
    EncodeReply,
    EncodeRequest,
    FramesRequest,
    InfoReply,
    PathsReply,
    RenderReply,
    RenderRequest,
    RunReply,
    RunRequest,
    WireArray,
    unpack,
)

SIZE = 64
STATE = {"stacks": [["red"], ["green", "blue"], ["yellow"]]}
FRAME_S = 0.2  # what the played encoder takes for a query of frames


def jpeg(width: int, height: int, seed: int = 0) -> bytes:
    """A smooth frame (tens of kB, as a camera's of a table would be, not megabytes of noise)."""
    rows, cols = np.mgrid[0:height, 0:width]
    pixels = np.stack([rows * 255 // height, cols * 255 // width, (rows + cols + seed) % 256], -1)
    buffer = io.BytesIO()
    Image.fromarray(pixels.astype(np.uint8)).save(buffer, format="JPEG", quality=85)
    return buffer.getvalue()


@pytest.fixture(scope="module")
def played(router_endpoint):
    """An encoder whose `frames` work is slow and queued at most 2 deep (as the real one's is
    bounded), a sim and a planner that answer at once; what each query brought is kept."""
    session = open_session(BusConfig(connect=[router_endpoint], open_timeout_s=5))
    seen: dict[str, list] = {"encode": [], "frames": [], "run": []}

    def info(_: bytes) -> InfoReply:
        return InfoReply(
            service="encoder", instance="played", task="box_stacking", model_id="m",
            image_size=SIZE, latent_dim=4, pid=0, uptime_s=1.0,
        )  # fmt: skip

    def encode(payload: bytes) -> EncodeReply:
        images = unpack(payload, EncodeRequest).images.numpy()
        seen["encode"].append(images.shape)
        return EncodeReply(latents=WireArray.of(np.zeros((len(images), 4), np.float32)))

    def frames(requests: list[FramesRequest]) -> list[EncodeReply]:
        time.sleep(FRAME_S)
        seen["frames"] += [r.frames for r in requests]
        latents = [np.zeros((len(r.frames), 4), np.float32) for r in requests]
        return [EncodeReply(latents=WireArray.of(z)) for z in latents]

    def render(payload: bytes) -> RenderReply:
        states = len(unpack(payload, RenderRequest).states)
        return RenderReply(images=WireArray.of(np.zeros((states, SIZE, SIZE, 3), np.uint8)))

    def run(payload: bytes) -> RunReply:
        seen["run"].append(unpack(payload, RunRequest).goal_image)
        none = WireArray.of(np.zeros((0, SIZE, SIZE, 3), np.uint8))
        return RunReply(success=False, reason="played", final_state=STATE, actions=[], images=none)

    def paths(_: bytes) -> PathsReply:
        none = WireArray.of(np.zeros((0, 4), np.float32))
        return PathsReply(paths=[], supports=[], node_ids=[], node_latents=none, model_id="m",
                          reason="played: no paths")  # fmt: skip

    parse = lambda payload: unpack(payload, FramesRequest)  # noqa: E731
    servers = []
    for service, operation, handler in [
        ("encoder", "info/played", info),
        ("encoder", "encode", encode),
        ("encoder", "frames", Batched(parse, frames, max_batch=1, max_queued=2)),
        ("sim", "render", render),
        ("sim", "run", run),
        ("planner", "paths", paths),
    ]:
        server = Server(session, service, f"{service}-played")
        server.serve(service_key(service, "box_stacking", operation), handler)
        servers.append(server)
    time.sleep(0.3)
    yield seen
    for server in servers:
        server.close()
    close_quietly(session)


@pytest.fixture(scope="module")
def gateway_url(gateway_with, played):
    yield from gateway_with(deadline_s=3.0)


def test_a_frame_reaches_the_encoder_as_the_bytes_the_client_sent(gateway_url, played):
    frame = jpeg(1280, 960)
    body = {
        "task": "box_stacking",
        "start": {"image": base64.b64encode(frame).decode()},
        "goal": {"state": STATE},
    }
    with httpx.Client(base_url=gateway_url, timeout=10) as http:
        reply = http.post("/plan", json=body)
    assert reply.status_code == 200, reply.text
    assert played["frames"][-1] == [frame]  # not decoded pixels: the JPEG itself
    assert played["encode"][-1] == (1, SIZE, SIZE, 3)  # the goal's render, a view


def test_an_execute_goal_frame_reaches_the_sim_as_the_bytes_the_client_sent(gateway_url, played):
    frame = jpeg(1280, 960, 3)
    body = {
        "task": "box_stacking",
        "start": {"state": STATE},
        "goal": {"image": base64.b64encode(frame).decode()},
    }
    with httpx.Client(base_url=gateway_url, timeout=10) as http:
        reply = http.post("/execute", json=body)
        bomb = http.post("/execute", json={**body, "goal": {"image": png_bomb()}})
    assert reply.status_code == 200, reply.text
    assert played["run"] == [frame]  # the JPEG itself, to be decoded where it is registered
    assert bomb.status_code == 422 and "goal.image" in bomb.text  # from its header, not sent


def png_bomb() -> str:
    """A 4096 x 4096 PNG of one colour: some kB that would decode to 50 MB."""
    buffer = io.BytesIO()
    Image.new("RGB", (4096, 4096), "gray").save(buffer, format="PNG")
    return base64.b64encode(buffer.getvalue()).decode()


def test_light_requests_are_answered_while_frames_flood_the_encoder(gateway_url, played):
    heavy = {
        "task": "box_stacking",
        "start": {"image": base64.b64encode(jpeg(2048, 1536, 1)).decode()},
        "goal": {"image": base64.b64encode(jpeg(2048, 1536, 2)).decode()},
    }
    light = {"task": "box_stacking", "start": {"state": STATE}, "goal": {"state": STATE}}

    def flood(_: int) -> list[tuple[int, str | None]]:
        answers = []
        with httpx.Client(base_url=gateway_url, timeout=30) as http:
            for _ in range(6):  # bounded: 8 clients x 6 pairs, each 0.2 s of the encoder's
                reply = http.post("/plan", json=heavy)
                answers.append((reply.status_code, reply.headers.get("retry-after")))
        return answers

    with ThreadPoolExecutor(8) as pool:
        floods = [pool.submit(flood, i) for i in range(8)]
        with httpx.Client(base_url=gateway_url, timeout=30) as http:
            lights = [http.post("/plan", json=light).status_code for _ in range(10)]
        heavies = [answer for f in floods for answer in f.result()]
    assert lights == [200] * 10  # every light request answered, none shed
    statuses = {status for status, _ in heavies}
    assert statuses <= {200, 429, 503}, heavies
    assert (200, None) in heavies  # frames still served
    assert all(retry == "1" for status, retry in heavies if status in (429, 503)), heavies
