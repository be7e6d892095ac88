"""Checks on incoming messages that name the field at fault."""

from __future__ import annotations

from typing import Any

import numpy as np

from shared.appearance import APPEARANCES, LEVELS
from shared.images import ImageError, decode_image, image_size
from shared.messages import WireArray
from shared.tasks.base import InvalidStateError, Task
from shared.workcell import FRAME_SIZE


class FieldError(ValueError):
    """A bad value in a request; `field` is its dotted path."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field}: {message}")
        self.field = field


def parse_state(task: Task, field: str, obj: Any) -> Any:
    """The task's state from JSON, or a FieldError naming `field` (or its unknown key).

    Keys the task's own JSON of the state lacks are refused: a misspelt key would otherwise be
    ignored silently.
    """
    try:
        state = task.parse_state(obj)
    except InvalidStateError as exc:
        raise FieldError(field if exc.key is None else f"{field}.{exc.key}", str(exc)) from None
    if isinstance(obj, dict):
        known = task.state_to_json(state)
        unknown = [key for key in obj if key not in known]
        if unknown:
            raise FieldError(
                f"{field}.{unknown[0]}", f"unknown key {unknown[0]!r}; a state has {sorted(known)}"
            )
    return state


MAX_FRAME = 4096  # pixels a side of a camera frame
MAX_FRAME_PIXELS = 4096 * 3072  # decoded pixels of one frame: a 12-megapixel camera's
# A JPEG frame is decoded reduced (by 2, 4 or 8, in the decoder) down to this shorter side: the
# simulated cell's own frames (FRAME_SIZE), so that the markers and the table view keep at
# least the pixels they have there (512 served the 2.2-times, 400 px frames before 2026-12-06).
FRAME_DETAIL = FRAME_SIZE


def frame_size(field: str, data: bytes) -> tuple[int, int]:
    """(width, height) a camera frame's PNG/JPEG bytes decode to, read from their header; a
    FieldError naming `field` for what `decode_frame` would refuse there (a decode bomb)."""
    try:
        return image_size(
            data, at_least=FRAME_DETAIL, max_side=MAX_FRAME, max_pixels=MAX_FRAME_PIXELS
        )
    except ImageError as exc:
        raise FieldError(field, str(exc)) from None


def decode_frame(field: str, data: bytes) -> np.ndarray:
    """A camera frame's pixels, a JPEG decoded reduced down to FRAME_DETAIL; none beyond
    MAX_FRAME_PIXELS (refused from the header)."""
    try:
        return decode_image(
            data, at_least=FRAME_DETAIL, max_side=MAX_FRAME, max_pixels=MAX_FRAME_PIXELS
        )
    except ImageError as exc:
        raise FieldError(field, str(exc)) from None


def check_frames(field: str, array: WireArray, max_rows: int | None = None) -> np.ndarray:
    """uint8 images (N, H, W, 3) of any size from 16 to MAX_FRAME a side, camera frames or
    images already in the table frame; with max_rows=None a single (H, W, 3)."""
    images = array.numpy()
    ndim = 3 if max_rows is None else 4
    if array.dtype != "|u1" or images.ndim != ndim or images.shape[-1] != 3:
        expected = "(H, W, 3)" if max_rows is None else "(N, H, W, 3)"
        raise FieldError(
            field, f"expected uint8 {expected}, got {array.dtype} {list(images.shape)}"
        )
    if not all(16 <= side <= MAX_FRAME for side in images.shape[-3:-1]):
        raise FieldError(
            field, f"images are 16 to {MAX_FRAME} pixels a side, got {list(images.shape[-3:-1])}"
        )
    if max_rows is not None and not 1 <= len(images) <= max_rows:
        raise FieldError(field, f"1 to {max_rows} images per request, got {len(images)}")
    return images


def check_task(requested: str, served: str) -> None:
    if requested != served:
        raise FieldError("task", f"this instance serves {served!r}, not {requested!r}")


def check_appearance(requested: str | None, default: str) -> str:
    """The level asked for (None: `default`, the model's training appearance)."""
    level = default if requested is None else requested
    if level not in APPEARANCES:
        raise FieldError(
            "appearance", f"unknown level {level!r}; known levels are {', '.join(LEVELS)}"
        )
    return level


def check_latents(
    field: str, array: WireArray, dim: int, max_rows: int | None = None, ndim: int = 2
) -> np.ndarray:
    """float32 latents of shape (N, dim) (or (dim,) with ndim=1), all finite."""
    z = array.numpy()
    expected = f"(N, {dim})" if ndim == 2 else f"({dim},)"
    if array.dtype != "<f4" or z.ndim != ndim or z.shape[-1] != dim:
        raise FieldError(field, f"expected float32 {expected}, got {array.dtype} {list(z.shape)}")
    if ndim == 2 and max_rows is not None and not 1 <= len(z) <= max_rows:
        raise FieldError(field, f"1 to {max_rows} rows per request, got {len(z)}")
    if not np.isfinite(z).all():
        raise FieldError(field, "contains NaN or infinity")
    return z.copy()  # writable, as torch wants it; the wire's buffer is read-only
