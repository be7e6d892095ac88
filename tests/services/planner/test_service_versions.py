"""A running planner takes a grown roadmap version while it answers, failing no request."""

import shutil
import threading
import time

import numpy as np

from services.planner import service as planner_service
from services.planner.grow import grow_model
from services.runtime import ModelInfo, ServiceContext
from services.sim.datagen import GenerateConfig, generate
from shared.messages import PathsReply, PathsRequest, WireArray, pack
from shared.settings import Settings


def test_a_grown_version_is_taken_under_load_without_a_failed_request(
    tiny_model, tmp_path, monkeypatch
):
    model = tmp_path / "model"
    shutil.copytree(tiny_model[0], model)
    experience = tmp_path / "experience"  # new tuples (its training data it holds already)
    generate(GenerateConfig(pairs=20, seed=7, image_size=32, workers=1), experience, progress=False)
    monkeypatch.setattr(planner_service, "RELOAD_S", 0.05)
    info = ModelInfo.read(model)
    context = ServiceContext("planner", "x", info, None, Settings())
    paths = planner_service.setup(context)["paths"]
    assert context.status["roadmap_version"] == "v1"
    z = np.zeros(info.latent_dim, np.float32)
    request = pack(
        PathsRequest(
            task=info.task,
            z_start=WireArray.of(z),
            z_goal=WireArray.of(z + 0.01),
            errors=WireArray.of(np.zeros((2, 3), np.float32)),
        )
    )
    seen: list[str] = []
    failures: list[BaseException] = []
    done = threading.Event()

    def load() -> None:
        while not done.is_set():
            try:
                reply = paths(request)
                assert isinstance(reply, PathsReply)
                seen.append(reply.roadmap_version)
            except BaseException as exc:
                failures.append(exc)

    caller = threading.Thread(target=load)
    caller.start()
    try:
        grow_model(model, [experience])
        for _ in range(400):  # the watcher looks every 0.05 s
            if seen and seen[-1] == "v2":
                break
            time.sleep(0.05)
    finally:
        done.set()
        caller.join()
        context.stopping.set()
    assert not failures
    assert seen[0] == "v1" and seen[-1] == "v2" == context.status["roadmap_version"]
    assert seen == sorted(seen)  # once switched, never back
