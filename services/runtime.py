"""What every service process does the same way: read the model, join zenoh, serve, stop cleanly."""

from __future__ import annotations

import hashlib
import logging
import os
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import zenoh

from services.encoder.checkpoint import WEIGHTS, read_vae_config
from services.planner.versions import roadmap_dir
from shared.appearance import CLEAN, trained_appearance
from shared.bus import (
    Operation,
    Server,
    close_quietly,
    new_instance_id,
    open_session,
    service_key,
    wait_for_stop_signal,
)
from shared.checkpoint import MANIFEST, CheckpointError, verify, weights_file
from shared.messages import InfoReply
from shared.settings import MODEL_PARTS, Settings

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ModelInfo:
    """The model folder every service of one deployment serves (vae/, roadmap/, apn/)."""

    directory: Path
    task: str
    model_id: str  # the first 12 hex digits of the VAE weights' sha256
    image_size: int
    latent_dim: int
    appearance: str = CLEAN  # the training data's look: the default for rendering to it

    @classmethod
    def read(cls, directory: Path | str, require_sealed: bool = False) -> ModelInfo:
        """The model's identity, after checking each part against its manifest: a part that
        was changed or half-written since it was sealed is refused, naming the file."""
        directory = Path(directory)
        folders = {part: directory / part for part in MODEL_PARTS}
        if folders["roadmap"].is_dir():
            folders["roadmap"] = roadmap_dir(directory)  # the version it plans with
        unsealed = [
            part for part, folder in folders.items() if folder.is_dir() and not verify(folder)
        ]
        if unsealed and require_sealed:
            raise CheckpointError(
                f"{directory}: {', '.join(unsealed)} not sealed (no {MANIFEST}); seal with "
                "python -m shared.checkpoint seal DIR FILE..."
            )
        if unsealed:
            log.warning("%s: %s not sealed: served unverified", directory, ", ".join(unsealed))
        config = read_vae_config(directory / "vae")
        declare_model_task(config)
        digest = hashlib.sha256(weights_file(directory / "vae", WEIGHTS).read_bytes())
        return cls(
            directory=directory,
            task=config["dataset"]["task"],
            model_id=digest.hexdigest()[:12],
            image_size=int(config["model"]["image_size"]),
            latent_dim=int(config["model"]["latent_dim"]),
            appearance=trained_appearance(config),
        )


def declare_model_task(vae_config: dict) -> None:
    """Make a task defined by its data known to this process (built-in tasks need nothing):
    the VAE's config records the spec of the dataset it was trained on."""
    spec = vae_config["dataset"].get("spec")
    if spec is not None:
        from shared.tasks import declare_task
        from shared.tasks.spec import TaskSpec
        from shared.workcell import Workcell

        markers = Workcell.from_json(vae_config["dataset"].get("markers"))
        declare_task(TaskSpec.from_json(spec), markers)


@dataclass
class ServiceContext:
    service: str
    instance: str
    model: ModelInfo
    session: zenoh.Session
    settings: Settings
    # What a service reports in its health answers beside its model (the planner's roadmap
    # version); it may change while serving.
    status: dict[str, str] = field(default_factory=dict)
    stopping: threading.Event = field(default_factory=threading.Event)  # set when it stops


# A service's setup loads its model and returns its handlers by operation name.
Setup = Callable[[ServiceContext], Mapping[str, Operation]]


def run_service(service: str, setup: Setup, settings: Settings, models: Sequence[Path] = ()) -> int:
    """Serve until SIGINT or SIGTERM. One torch thread by default: the services share the CPU.

    `models` (default: `settings.model_dir`): the model folders it serves, one a task. One
    process for several tasks shares the interpreter, torch and the zenoh session among them
    (`lsr up` runs one per role): each task's operations keep their own worker threads."""
    import torch

    torch.set_num_threads(settings.torch_threads)
    instance = settings.instance or new_instance_id()
    infos = [
        ModelInfo.read(directory, settings.require_sealed_model)
        for directory in (models or [settings.model_dir])
    ]
    tasks = [model.task for model in infos]
    if len(set(tasks)) != len(tasks):
        raise ValueError(f"two model folders serve the same task: {tasks}")
    session = open_session(settings.bus())
    server = Server(session, service, instance)
    started = time.monotonic()
    contexts = []
    for model in infos:
        context = ServiceContext(service, instance, model, session, settings)
        contexts.append(context)
        for operation, handler in setup(context).items():
            server.serve(service_key(service, model.task, operation), handler)
        # Health answers come from every instance (the gateway lists them): a key each.
        info = partial(_info, context, started)
        server.serve(service_key(service, model.task, f"info/{instance}"), info, per_instance=False)
        log.info("%s %s serving %s (model %s)", service, instance, model.task, model.model_id)
        print(f"{service} {instance} ready: task {model.task}, model {model.model_id}", flush=True)
    wait_for_stop_signal()
    for context in contexts:
        context.stopping.set()
    server.close()
    close_quietly(session)
    return 0


def _info(context: ServiceContext, started: float, _: bytes) -> InfoReply:
    """A health answer: what the gateway's /health lists for this instance and task."""
    return InfoReply(
        service=context.service,
        instance=context.instance,
        task=context.model.task,
        model_id=context.model.model_id,
        image_size=context.model.image_size,
        latent_dim=context.model.latent_dim,
        pid=os.getpid(),
        uptime_s=round(time.monotonic() - started, 3),
        roadmap_version=context.status.get("roadmap_version"),
    )
