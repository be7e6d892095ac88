"""The encoder service: images -> latent means, latents -> images.

Decoded roadmap nodes are cached by the callers (`shared.client.PlanningClient`), not here.
"""

from __future__ import annotations

from services.encoder.checkpoint import decode_latents, encode_images, load_vae
from services.runtime import ServiceContext
from shared.bus import Handler
from shared.messages import (
    DecodeReply,
    DecodeRequest,
    EncodeReply,
    EncodeRequest,
    WireArray,
    unpack,
)
from shared.validation import check_images, check_latents, check_task

MAX_BATCH = 256


def setup(context: ServiceContext) -> dict[str, Handler]:
    vae, _ = load_vae(context.model.directory / "vae")
    size, dim, task = context.model.image_size, context.model.latent_dim, context.model.task

    def encode(payload: bytes) -> EncodeReply:
        request = unpack(payload, EncodeRequest)
        check_task(request.task, task)
        images = check_images("images", request.images, size, max_rows=MAX_BATCH)
        return EncodeReply(latents=WireArray.of(encode_images(vae, images)[0]))

    def decode(payload: bytes) -> DecodeReply:
        request = unpack(payload, DecodeRequest)
        check_task(request.task, task)
        latents = check_latents("latents", request.latents, dim, max_rows=MAX_BATCH)
        return DecodeReply(images=WireArray.of(decode_latents(vae, latents)))

    return {"encode": encode, "decode": decode}
