"""What the latency benchmarks share: /plan request bodies of rendered states, percentiles, and
the Server-Timing header read back."""

from __future__ import annotations

import base64
import io
import sys
from pathlib import Path

import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.sim.workcell import Observer
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


def camera_bytes(
    frame: np.ndarray, codec: str = "JPEG", side: int | None = None, quality: int = 90
) -> bytes:
    """A frame as a camera would send it: `side` px a side (a higher-resolution camera: resized
    bicubic), JPEG at `quality` or PNG."""
    image = Image.fromarray(np.asarray(frame, np.uint8))
    if side is not None and image.size != (side, side):
        image = image.resize((side, side), Image.Resampling.BICUBIC)
    buffer = io.BytesIO()
    image.save(buffer, format=codec, **({"quality": quality} if codec == "JPEG" else {}))
    return buffer.getvalue()


def request_bodies(
    pairs: int,
    size: int,
    seed: int,
    frames: bool = False,
    appearance: str | None = None,
    jpeg_quality: int | None = None,
    fixed_camera: bool = False,
    side: int | None = None,
) -> list[dict]:
    """Image-to-image box-stacking /plan bodies between random states, 8 plans at most, at
    `appearance` (default: the task's own): the views a model is given (registered where the
    look is a camera's), or with `frames` the cell camera's whole frames (registered by the
    encoder); PNG, or JPEG at `jpeg_quality`. Each state is a new look (lights, camera pose:
    a camera moved since the last frame), or with `fixed_camera` one look for all (a cell's);
    frames resized to `side` px as a camera of that resolution would give them."""
    task = get_task("box_stacking")
    rng, looks = np.random.default_rng(seed), np.random.default_rng(seed + 1)  # same states
    bodies = []
    with make_world("box_stacking", size, appearance=appearance) as world:
        observer = Observer(world, register=not frames)
        for _ in range(pairs):
            images = []
            for state in (task.sample_state(rng), task.sample_state(rng)):
                world.reset(state, np.random.default_rng(seed) if fixed_camera else looks)
                image = observer.see()
                if jpeg_quality is None and side is None:
                    images.append(png_b64(image))
                else:
                    codec = "PNG" if jpeg_quality is None else "JPEG"
                    data = camera_bytes(image, codec, side, quality=jpeg_quality or 90)
                    images.append(base64.b64encode(data).decode())
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
