"""The encoder service: images -> latent means (and reconstruction errors), latents -> images.

Camera frames come compressed (`frames`, `register`) and are decoded and registered here, in a
worker and a bounded queue of their own, so that a flood of them never delays images at the
model's size (`encode`: renders of states, registered images).

Encoding is batched: the images of every encode query queued at once go through one forward
pass. Decoded roadmap nodes are cached by the callers (`shared.client.PlanningClient`), not here.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from services.encoder.checkpoint import decode_latents, load_vae
from services.planner.knowing import look
from services.runtime import ServiceContext
from shared.bus import Batched, Operation, lower_priority
from shared.messages import (
    DecodeReply,
    DecodeRequest,
    EncodeReply,
    EncodeRequest,
    FramesRequest,
    RegisterReply,
    WireArray,
    unpack,
)
from shared.registration import Registration, to_table_frame
from shared.tasks import get_task
from shared.validation import (
    FieldError,
    check_frames,
    check_latents,
    check_task,
    decode_frame,
    frame_size,
)

MAX_BATCH = 256
# Camera frames are heavy work (a 4096 px JPEG, 0.8 megapixels decoded reduced: about 20 ms
# idle to decode and register) with a queue of their own, bounded by the pixels it holds (read
# from the frames' headers; about 20 such frames, 0.4 s of work): the next query is told to
# come back (Batched.max_queued), and images at the model's size (`encode`) never wait behind
# frames. Its worker runs at a lower priority: where both wait for a core, `encode` gets it.
MAX_QUEUED_MEGAPIXELS = 16.0
FRAMES_NICE = 10


def megapixels(payload: bytes) -> float:
    """What a query of frames costs: the pixels its frames decode to (a JPEG reduced)."""
    request = unpack(payload, FramesRequest)
    sizes = [frame_size(f"frames.{i}", data) for i, data in enumerate(request.frames)]
    return sum(w * h for w, h in sizes) / 1e6


def setup(context: ServiceContext) -> dict[str, Operation]:
    vae, _ = load_vae(context.model.directory / "vae")
    size, dim, task = context.model.image_size, context.model.latent_dim, context.model.task
    registration = Registration(get_task(task).workcell, size)  # every frame, before the model

    def parse_encode(payload: bytes) -> tuple[np.ndarray, list[str | None]]:
        request = unpack(payload, EncodeRequest)
        check_task(request.task, task)
        images = check_frames("images", request.images, MAX_BATCH)
        if images.shape[1:3] != (size, size):
            raise FieldError(
                "images",
                f"images are {size} x {size} (the model's size); camera frames of "
                f"{images.shape[2]} x {images.shape[1]} go compressed to the frames operation",
            )
        return images, [None] * len(images)

    # A query's frames (a plan's start and goal) are decoded and registered side by side, the
    # first in the frames worker, the others in a helper of its priority: decoders and OpenCV
    # let go of the GIL.
    helper = ThreadPoolExecutor(1, "frames-helper", lower_priority, (FRAMES_NICE,))

    def table_view(i: int, data: bytes) -> tuple[np.ndarray, list[str | None]]:
        return to_table_frame(registration, [decode_frame(f"frames.{i}", data)])

    def parse_frames(payload: bytes) -> tuple[np.ndarray, list[str | None]]:
        """Decoded and registered here, in the frames worker: never in front of `encode`."""
        request = unpack(payload, FramesRequest)
        check_task(request.task, task)
        first, *rest = request.frames
        later = [helper.submit(table_view, i, data) for i, data in enumerate(rest, start=1)]
        views = [table_view(0, first), *(job.result() for job in later)]
        return np.concatenate([v for v, _ in views]), [r for _, reasons in views for r in reasons]

    def encode(batches: list[tuple[np.ndarray, list[str | None]]]) -> list[EncodeReply]:
        images = np.concatenate([registered for registered, _ in batches])
        latents, errors = look(vae, images)  # errors: for knowing the images
        ends = np.cumsum([len(registered) for registered, _ in batches])[:-1]
        return [
            EncodeReply(
                latents=WireArray.of(z),
                errors=WireArray.of(e.astype(np.float32)),
                refused=reasons if any(reasons) else None,
            )
            for z, e, (_, reasons) in zip(
                np.split(latents, ends), np.split(errors, ends), batches, strict=True
            )
        ]

    def register(batches: list[tuple[np.ndarray, list[str | None]]]) -> list[RegisterReply]:
        """Frames in the table frame, for what is stored rather than encoded (experience)."""
        return [
            RegisterReply(images=WireArray.of(images), refused=refused if any(refused) else None)
            for images, refused in batches
        ]

    def decode(payload: bytes) -> DecodeReply:
        request = unpack(payload, DecodeRequest)
        check_task(request.task, task)
        latents = check_latents("latents", request.latents, dim, max_rows=MAX_BATCH)
        images = WireArray.of(decode_latents(vae, latents))
        return DecodeReply(images=images, model_id=context.model.model_id)

    frames_queue = {"max_queued": MAX_QUEUED_MEGAPIXELS, "nice": FRAMES_NICE, "cost": megapixels}
    return {
        "encode": Batched(parse_encode, encode, max_batch=8),
        "frames": Batched(parse_frames, encode, max_batch=2, **frames_queue),
        "decode": decode,
        "register": Batched(parse_frames, register, max_batch=1, **frames_queue),
    }
