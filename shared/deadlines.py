"""The deadline of the request a thread works for, so that long work stops when nobody waits.

A service's worker sets it around each request (`working_until`); code deep inside (a physics
loop, say) calls `check_deadline()` now and then, and gives up with DeadlineExceeded once the
caller's budget has run out, instead of finishing work whose answer nobody would read.
"""

from __future__ import annotations

import contextvars
import time
from collections.abc import Iterator
from contextlib import contextmanager

_deadline: contextvars.ContextVar[float | None] = contextvars.ContextVar("deadline", default=None)


class DeadlineExceeded(RuntimeError):
    """The caller's deadline passed while its request was being worked on."""


@contextmanager
def working_until(deadline: float | None) -> Iterator[None]:
    """Run the block for a caller who waits until `deadline` (time.monotonic); None: for ever."""
    token = _deadline.set(deadline)
    try:
        yield
    finally:
        _deadline.reset(token)


def check_deadline() -> None:
    deadline = _deadline.get()
    if deadline is not None and time.monotonic() > deadline:
        raise DeadlineExceeded(
            f"the caller's deadline passed {time.monotonic() - deadline:.2f} s ago"
        )
