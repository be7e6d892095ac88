"""Camera frames decoded and registered in a process of the encoder's own, beside its frames
worker: a plan's start and goal frames then take two cores where a thread of the same process
took about one and a half (Python holds the GIL between OpenCV's calls). Measured on 2026-12-06:
two 400 px PNG frames 2.5-3.0 ms side by side against 3.4-3.7 ms with a helper thread and 4.8 ms
one after the other (one frame 2.4 ms).

The helper starts with the first query of two or more frames (about 66 MB resident: an encoder
that is never sent frames has none), speaks msgpack over its stdin and stdout, each message after
its length (4 bytes, little-endian; no pickle), and ends when its stdin closes, so it never
outlives the encoder.
"""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
import threading
from typing import IO

import numpy as np
from pydantic import Field

from shared.messages import Frame, Message, WireArray, pack, unpack
from shared.registration import Registration, to_table_frame
from shared.validation import FieldError, decode_frame
from shared.workcell import Workcell

Views = tuple[np.ndarray, list[str | None]]  # registered views (N, S, S, 3), why any was refused
_LENGTH = struct.Struct("<I")


class FramesJob(Message):
    first: int  # the request index of frames[0]: errors name the request's own field
    frames: list[Frame]


class FramesDone(Message):
    images: WireArray | None = None
    refused: list[str | None] = Field(default_factory=list)
    field: str | None = None  # a frame that could not be decoded (images None), and why
    error: str | None = None


def table_views(registration: Registration, first: int, frames: list[bytes]) -> Views:
    """Each frame decoded and registered; FieldError names a frame that cannot be decoded."""
    views = [
        to_table_frame(registration, [decode_frame(f"frames.{i}", data)])
        for i, data in enumerate(frames, start=first)
    ]
    return np.concatenate([v for v, _ in views]), [r for _, reasons in views for r in reasons]


class Frames:
    """Decodes and registers a query's frames: the first half here, in the calling thread, the
    rest in the helper process, where it is free (another thread's job holds it: all here)."""

    def __init__(self, workcell: Workcell | None, size: int, nice: int) -> None:
        self.registration = Registration(workcell, size)
        settings = {"workcell": workcell and workcell.to_json(), "size": size, "nice": nice}
        self._argv = [sys.executable, "-m", __name__, json.dumps(settings)]
        self._lock = threading.Lock()  # the process's pipes, from a job sent to its reply
        self._process: subprocess.Popen[bytes] | None = None  # started by the first query

    def views(self, frames: list[bytes]) -> Views:
        half = (len(frames) + 1) // 2
        if len(frames) == 1 or not self._lock.acquire(blocking=False):
            return table_views(self.registration, 0, frames)
        try:
            sent = self._send(FramesJob(first=half, frames=frames[half:]))
            if not sent:  # no helper running (the first query, or it died): one for the next
                self._process = subprocess.Popen(
                    self._argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE
                )
            try:
                mine = table_views(self.registration, 0, frames[:half])
            finally:
                done = self._receive() if sent else None  # the reply read whatever happens here
        finally:
            self._lock.release()
        if done is None:  # no helper: its half here
            rest = table_views(self.registration, half, frames[half:])
        elif done.images is None:
            raise FieldError(done.field or "frames", done.error or "cannot be decoded")
        else:
            rest = done.images.numpy(), done.refused
        return np.concatenate([mine[0], rest[0]]), mine[1] + rest[1]

    def _send(self, job: FramesJob) -> bool:
        """The job sent to a running helper; False where none runs."""
        if self._process is None or self._process.poll() is not None:
            return False
        assert self._process.stdin is not None
        try:
            _write(self._process.stdin, pack(job))
        except OSError:
            self._stop()
            return False
        return True

    def _receive(self) -> FramesDone | None:
        assert self._process is not None and self._process.stdout is not None
        payload = _read(self._process.stdout)
        if payload is None:
            self._stop()
            return None
        return unpack(payload, FramesDone)

    def _stop(self) -> None:
        if self._process is not None:
            self._process.kill()
            self._process.wait()
            self._process = None

    def close(self) -> None:
        """Ends the helper process (it also ends by itself when the encoder's process does)."""
        with self._lock:
            if self._process is not None and self._process.stdin is not None:
                self._process.stdin.close()
                self._process.wait(5)
                self._process = None


def _write(stream: IO[bytes], payload: bytes) -> None:
    stream.write(_LENGTH.pack(len(payload)) + payload)
    stream.flush()


def _read(stream: IO[bytes]) -> bytes | None:
    """One message, or None where the stream ended."""
    head = stream.read(_LENGTH.size)
    if len(head) < _LENGTH.size:
        return None
    (length,) = _LENGTH.unpack(head)
    payload = stream.read(length)
    return payload if len(payload) == length else None


def main() -> None:
    """The helper process: jobs from stdin, views to stdout, until stdin closes."""
    settings = json.loads(sys.argv[1])
    os.nice(settings["nice"])
    workcell = Workcell.from_json(settings["workcell"]) if settings["workcell"] else None
    registration = Registration(workcell, settings["size"])
    source, sink = sys.stdin.buffer, sys.stdout.buffer
    while (payload := _read(source)) is not None:
        job = unpack(payload, FramesJob)
        try:
            images, refused = table_views(registration, job.first, job.frames)
            done = FramesDone(images=WireArray.of(images), refused=refused)
        except FieldError as exc:
            done = FramesDone(field=exc.field, error=str(exc).removeprefix(f"{exc.field}: "))
        _write(sink, pack(done))


if __name__ == "__main__":
    main()
