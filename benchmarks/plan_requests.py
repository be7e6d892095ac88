"""What the latency benchmarks share: /plan request bodies of rendered states, percentiles, and
the Server-Timing header read back."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.sim.worlds import make_world
from shared.images import png_b64
from shared.tasks import get_task


def percentiles(seconds: list[float]) -> dict[str, float]:
    ms = np.array(seconds) * 1e3
    return {
        "p50_ms": round(float(np.percentile(ms, 50)), 2),
        "p99_ms": round(float(np.percentile(ms, 99)), 2),
        "mean_ms": round(float(ms.mean()), 2),
    }


def request_bodies(pairs: int, size: int, seed: int, frames: bool = False) -> list[dict]:
    """Image-to-image box-stacking /plan bodies between random states, 8 plans at most;
    `frames`: the cell camera's whole frames (registered by the encoder), not the views."""
    task = get_task("box_stacking")
    rng = np.random.default_rng(seed)
    bodies = []
    with make_world("box_stacking", size) as world:
        for _ in range(pairs):
            images = []
            for state in (task.sample_state(rng), task.sample_state(rng)):
                world.reset(state, rng)
                images.append(png_b64(world.frame() if frames else world.render()))
            bodies.append(
                {
                    "task": "box_stacking",
                    "start": {"image": images[0]},
                    "goal": {"image": images[1]},
                    "max_plans": 8,
                }
            )
    return bodies


def server_timing(header: str) -> dict[str, float]:
    """`encode;dur=8.1, encode-handler;dur=6.9, ...` -> {"encode": 8.1, ...} (ms)."""
    return {name: float(ms) for name, ms in (m.split(";dur=") for m in header.split(", "))}
