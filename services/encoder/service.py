"""The encoder service: images -> latent means, latents -> images (with a decode cache)."""

from __future__ import annotations

from collections import OrderedDict

import numpy as np
import torch

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


class DecodeCache:
    """Roadmap nodes come back in every plan: decode each latent once, keep the newest ones."""

    def __init__(self, capacity: int = 4096) -> None:
        self.capacity = capacity
        self._images: OrderedDict[bytes, np.ndarray] = OrderedDict()

    def decode(self, vae: torch.nn.Module, latents: np.ndarray) -> np.ndarray:
        keys = [row.tobytes() for row in latents]
        missing = [key for key in dict.fromkeys(keys) if key not in self._images]
        if missing:
            rows = np.stack([np.frombuffer(key, dtype=np.float32) for key in missing])
            self._images.update(zip(missing, decode_latents(vae, rows), strict=True))
        for key in keys:
            self._images.move_to_end(key)
        images = np.stack([self._images[key] for key in keys])
        while len(self._images) > self.capacity:
            self._images.popitem(last=False)
        return images


def setup(context: ServiceContext) -> dict[str, Handler]:
    vae, _ = load_vae(context.model.directory / "vae")
    size, dim, task = context.model.image_size, context.model.latent_dim, context.model.task
    cache = DecodeCache()

    def encode(payload: bytes) -> EncodeReply:
        request = unpack(payload, EncodeRequest)
        check_task(request.task, task)
        images = check_images("images", request.images, size, max_rows=MAX_BATCH)
        return EncodeReply(latents=WireArray.of(encode_images(vae, images)[0]))

    def decode(payload: bytes) -> DecodeReply:
        request = unpack(payload, DecodeRequest)
        check_task(request.task, task)
        latents = check_latents("latents", request.latents, dim, max_rows=MAX_BATCH)
        return DecodeReply(images=WireArray.of(cache.decode(vae, latents)))

    return {"encode": encode, "decode": decode}
