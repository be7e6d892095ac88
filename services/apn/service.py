"""The APN service: the action between consecutive latent states, with its confidence."""

from __future__ import annotations

import torch

from services.apn.train import load_apn, propose
from services.runtime import ServiceContext
from shared.bus import Handler
from shared.messages import ProposeReply, ProposeRequest, unpack
from shared.tasks import get_task
from shared.validation import FieldError, check_latents, check_task

MAX_PAIRS = 1024


def setup(context: ServiceContext) -> dict[str, Handler]:
    apn, _ = load_apn(context.model.directory / "apn")
    task = get_task(context.model.task)
    dim = context.model.latent_dim

    def propose_actions(payload: bytes) -> ProposeReply:
        request = unpack(payload, ProposeRequest)
        check_task(request.task, context.model.task)
        z_from = check_latents("z_from", request.z_from, dim, max_rows=MAX_PAIRS)
        z_to = check_latents("z_to", request.z_to, dim, max_rows=MAX_PAIRS)
        if len(z_from) != len(z_to):
            raise FieldError("z_to", f"{len(z_to)} rows for {len(z_from)} in z_from")
        with torch.inference_mode():
            arrays, confidences = propose(apn, z_from, z_to)
        actions = [task.array_to_action(a) for a in arrays]
        return ProposeReply(
            actions=[None if a is None else task.action_to_json(a) for a in actions],
            confidences=[float(c) for c in confidences],
        )

    return {"propose": propose_actions}
