"""What one camera frame costs on its way to a model: decoding (as the gateway decodes a frame)
and registration, by frame size and codec, in one process on one core.

Renders `--frames` random states of each task at `camera` (the cell's frame, `FRAME_SIZE` px),
resizes each to every `--sides` (as a higher-resolution camera would give them), encodes it as
JPEG (quality 90) and PNG, and times, in the order a robot's camera sends them (one fixed
camera: the markers are tracked from the last frame; a camera that moved between frames:
`bench_registration.py`'s "new look"): decoding (`decode_image` with the gateway's FRAME_DETAIL
and MAX_FRAME_PIXELS; a PNG beyond them is refused, not timed) and `Registration.register`.
Prints p50 / p99 in ms per task, side and codec.

    .venv/bin/python benchmarks/bench_frame_cost.py [--tasks box_stacking] [--frames 20]
        [--sides 720 1280 2048 4096] [--json runs/frame_cost.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from plan_requests import camera_bytes

from services.sim.worlds import make_world
from shared.images import ImageError, decode_image
from shared.registration import Registration
from shared.validation import FRAME_DETAIL, MAX_FRAME_PIXELS


def frames_of(task: str, count: int, seed: int) -> list[np.ndarray]:
    """Random states seen by one camera: one look (pose, lights), the image draws changing."""
    rng = np.random.default_rng(seed)
    with make_world(task, 64, appearance="camera") as world:
        world.reset(world.task.sample_state(rng), rng)  # draws the look
        frames = [world.frame()]
        for _ in range(count - 1):
            world.world.reset(world.task.sample_state(rng), rng)  # the same look
            frames.append(world.frame())
    return frames


def ms(times: list[float]) -> dict[str, float]:
    return {
        "p50": round(1e3 * float(np.median(times)), 2),
        "p99": round(1e3 * float(np.quantile(times, 0.99)), 2),
    }


def measure(task: str, frames: list[np.ndarray], side: int, codec: str, rounds: int) -> dict:
    data = [camera_bytes(f, codec, side) for f in frames]
    registration = Registration(make_world(task, 64).task.workcell, 64)
    decode_s, register_s, decoded_side = [], [], None
    for _ in range(rounds):
        for blob in data:
            started = time.perf_counter()
            try:
                frame = decode_image(blob, at_least=FRAME_DETAIL, max_pixels=MAX_FRAME_PIXELS)
            except ImageError:
                return {"refused": True, "kB": round(np.mean([len(b) for b in data]) / 1e3, 1)}
            decoded = time.perf_counter()
            registration.register(frame)
            decode_s.append(decoded - started)
            register_s.append(time.perf_counter() - decoded)
            decoded_side = frame.shape[0]
    return {
        "kB": round(np.mean([len(b) for b in data]) / 1e3, 1),
        "decoded_side": decoded_side,
        "decode_ms": ms(decode_s),
        "register_ms": ms(register_s),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=["box_stacking"])
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--sides", type=int, nargs="+", default=[720, 1280, 2048, 4096])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seed", type=int, default=48)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    results = {}
    print("| task | side | codec | kB | decoded side | decode p50 / p99 ms | "
          "register p50 / p99 ms |")  # fmt: skip
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for task in args.tasks:
        frames = frames_of(task, args.frames, args.seed)
        for side in args.sides:
            for codec in ("JPEG", "PNG"):
                r = measure(task, frames, side, codec, args.rounds)
                results[f"{task}/{side}/{codec}"] = r
                if r.get("refused"):
                    print(f"| {task} | {side} | {codec} | {r['kB']} | refused: over "
                          f"{MAX_FRAME_PIXELS} pixels | - | - |")  # fmt: skip
                    continue
                d, g = r["decode_ms"], r["register_ms"]
                cells = f"{d['p50']} / {d['p99']} | {g['p50']} / {g['p99']}"
                print(f"| {task} | {side} | {codec} | {r['kB']} | {r['decoded_side']} | {cells} |",
                      flush=True)  # fmt: skip
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
