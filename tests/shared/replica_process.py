"""A decoder replica in its own process, for tests that stop and kill it (not a test module).

Usage: python replica_process.py ENDPOINT INSTANCE. Answers `lsr/decoder/t/decode` with images
whose every byte is the first letter of INSTANCE; prints "ready" once serving.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from shared.bus import BusConfig, Server, open_session, service_key
from shared.messages import DecodeReply, DecodeRequest, WireArray, unpack


def main(endpoint: str, instance: str) -> None:
    session = open_session(BusConfig(connect=[endpoint], open_timeout_s=10))
    server = Server(session, "decoder", instance)

    def decode(payload: bytes) -> DecodeReply:
        rows = len(unpack(payload, DecodeRequest).latents.numpy())
        time.sleep(0.02)  # some work, so that queries queue under load
        return DecodeReply(
            images=WireArray.of(np.full((rows, 2, 2, 3), ord(instance[0]), np.uint8))
        )

    server.serve(service_key("decoder", "t", "decode"), decode)
    print("ready", flush=True)
    while True:
        time.sleep(1)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
