"""The encoder service: images -> latent means (and reconstruction errors), latents -> images.

Encoding is batched: the images of every encode query queued at once go through one forward
pass. Decoded roadmap nodes are cached by the callers (`shared.client.PlanningClient`), not here.
"""

from __future__ import annotations

import numpy as np

from services.encoder.checkpoint import decode_latents, load_vae
from services.planner.knowing import look
from services.runtime import ServiceContext
from shared.bus import Batched, Operation
from shared.messages import (
    DecodeReply,
    DecodeRequest,
    EncodeReply,
    EncodeRequest,
    RegisterReply,
    RegisterRequest,
    WireArray,
    unpack,
)
from shared.registration import Registration, to_table_frame
from shared.tasks import get_task
from shared.validation import check_frames, check_latents, check_task

MAX_BATCH = 256


def setup(context: ServiceContext) -> dict[str, Operation]:
    vae, _ = load_vae(context.model.directory / "vae")
    size, dim, task = context.model.image_size, context.model.latent_dim, context.model.task
    registration = Registration(get_task(task).workcell, size)  # every image, before the model

    def parse_encode(payload: bytes) -> tuple[np.ndarray, list[str | None]]:
        request = unpack(payload, EncodeRequest)
        check_task(request.task, task)
        return to_table_frame(registration, check_frames("images", request.images, MAX_BATCH))

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

    def register(payload: bytes) -> RegisterReply:
        """Images in the table frame, for what is stored rather than encoded (experience)."""
        request = unpack(payload, RegisterRequest)
        check_task(request.task, task)
        images, refused = to_table_frame(
            registration, check_frames("images", request.images, MAX_BATCH)
        )
        return RegisterReply(images=WireArray.of(images), refused=refused if any(refused) else None)

    def decode(payload: bytes) -> DecodeReply:
        request = unpack(payload, DecodeRequest)
        check_task(request.task, task)
        latents = check_latents("latents", request.latents, dim, max_rows=MAX_BATCH)
        images = WireArray.of(decode_latents(vae, latents))
        return DecodeReply(images=images, model_id=context.model.model_id)

    return {
        "encode": Batched(parse_encode, encode, max_batch=8),
        "decode": decode,
        "register": register,
    }
