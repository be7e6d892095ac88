"""Checks on incoming messages that name the field at fault."""

from __future__ import annotations

import numpy as np

from shared.messages import WireArray


class FieldError(ValueError):
    """A bad value in a request; `field` is its dotted path."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field}: {message}")
        self.field = field


def check_task(requested: str, served: str) -> None:
    if requested != served:
        raise FieldError("task", f"this instance serves {served!r}, not {requested!r}")


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
    return z
