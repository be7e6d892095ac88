"""What registration costs a /plan: camera frames against table-frame images, side by side.

Starts the stack (`lsr up`'s launcher) with the shipped model and sends image-to-image /plan
requests at concurrency 1 between the same random states, once as the views at the model's size
(taken as in the table frame already: registered here) and as the cell camera's whole frames
(`FRAME_SIZE` px, as PNG and as JPEG at quality 90, sent to the encoder as those bytes, which
decodes and registers them), at the `camera` look by default (a camera's noise: a 400 px
frame's PNG was 110 kB, at `clean` 9 kB): from a fixed camera (one look for every state: a
cell's, whose markers registration tracks from frame to frame) and from a camera that moved
before every frame (each state a new look: the markers are looked for again), in alternating
rounds, since this shared VM drifts from run to run. Prints p50 / p99 of each, the encoder's
handler time (which holds the decoding and registration), the request sizes, and registration
alone per frame in one process.

    .venv/bin/python benchmarks/bench_plan_frames.py [--rounds 6] [--per-round 100] [--pairs 50]
        [--concurrency 1] [--appearance camera] [--side 720]
"""

from __future__ import annotations

import argparse
import base64
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_plan_latency import through_stack  # noqa: E402
from plan_requests import request_bodies  # noqa: E402

from services.sim.workcell import FRAME_SIZE  # noqa: E402
from services.stack import Stack, StackConfig, free_port  # noqa: E402
from shared.images import decode_image  # noqa: E402
from shared.registration import Registration  # noqa: E402
from shared.tasks import get_task  # noqa: E402


def registration_alone(bodies: list[dict], size: int) -> dict[str, float]:
    """Decoding and registering one frame, in one process (ms)."""
    registration = Registration(get_task("box_stacking").workcell, size)
    frames = [
        decode_image(base64.b64decode(b[end]["image"])) for b in bodies for end in ("start", "goal")
    ]
    times = []
    for frame in frames * 3:
        started = time.perf_counter()
        registration.register(frame)
        times.append((time.perf_counter() - started) * 1e3)
    return {
        "p50_ms": round(float(np.median(times)), 2),
        "p99_ms": round(float(np.percentile(times, 99)), 2),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, default=ROOT / "models" / "box_stacking")
    parser.add_argument("--rounds", type=int, default=6)
    parser.add_argument("--per-round", type=int, default=100)
    parser.add_argument("--pairs", type=int, default=50)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--concurrency", type=int, default=1, help="clients at once")
    parser.add_argument(
        "--appearance", default="camera", help="the look of the states' images (the model's)"
    )
    parser.add_argument(
        "--side", type=int, default=FRAME_SIZE, help="frames resized to this (a camera's pixels)"
    )
    args = parser.parse_args()
    same = {"pairs": args.pairs, "size": 64, "seed": args.seed, "appearance": args.appearance}
    frames = {**same, "frames": True, "side": None if args.side == FRAME_SIZE else args.side}
    px = args.side
    kinds = {
        "views (64 px)": request_bodies(**same),
        f"frames ({px} px)": request_bodies(**frames, fixed_camera=True),
        f"frames ({px} px JPEG 90)": request_bodies(**frames, jpeg_quality=90, fixed_camera=True),
        f"frames, the camera moved ({px} px)": request_bodies(**frames),
        f"frames, the camera moved ({px} px JPEG 90)": request_bodies(**frames, jpeg_quality=90),
    }
    sizes = {k: int(np.median([len(b["start"]["image"]) for b in v])) for k, v in kinds.items()}
    for kind in (f"frames ({px} px)", f"frames, the camera moved ({px} px)"):
        print(f"registration alone, {kind}:", json.dumps(registration_alone(kinds[kind], 64)))
    runs: dict[str, list[dict]] = {kind: [] for kind in kinds}
    with tempfile.TemporaryDirectory() as logs:
        config = StackConfig(
            port=free_port(), zenoh_port=free_port(), models=(args.model,), log_dir=Path(logs)
        )
        with Stack(config) as stack:
            stack.start()
            stack.wait_healthy(90)
            for _ in range(args.rounds):
                for kind, bodies in kinds.items():
                    runs[kind].append(
                        through_stack(config.url, bodies, args.per_round, args.concurrency)
                    )
    print(
        f"model {args.model}, {args.rounds} rounds of {args.per_round} requests each, "
        f"concurrency {args.concurrency}, images at {args.appearance}"
    )
    print(
        "| images | base64 bytes (p50) | errors | /plan p50 / p99 (ms) | requests/s "
        "| encode handler p50 (ms) |"
    )
    print("| --- | --- | --- | --- | --- | --- |")
    summary = {}
    for kind, rounds in runs.items():
        p50 = float(np.median([r["p50_ms"] for r in rounds]))
        p99 = float(np.median([r["p99_ms"] for r in rounds]))
        rate = float(np.median([r["requests_per_s"] for r in rounds]))
        # views go to the encoder's `encode`, frames (compressed) to its `frames` operation
        operation = "frames" if "frames" in rounds[0]["p50_breakdown_ms"] else "encode"
        handler = float(np.median([r["p50_breakdown_ms"][f"{operation}-handler"] for r in rounds]))
        errors = sum(r["errors"] for r in rounds)
        summary[kind] = {
            "p50_ms": p50,
            "p99_ms": p99,
            "requests_per_s": rate,
            "encode_handler_ms": handler,
            "errors": errors,
        }
        print(
            f"| {kind} | {sizes[kind]} | {errors} | {p50:.1f} / {p99:.1f} | {rate:.1f} "
            f"| {handler:.1f} |"
        )
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
