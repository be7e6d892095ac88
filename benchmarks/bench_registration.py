"""Registration to the table frame (issue 38): markers found, homography error against the
renderer's true camera pose, and what registration does to a model's view of an image.

Usage:
    .venv/bin/python benchmarks/bench_registration.py [--tasks box_stacking cloth_folding]
        [--states 100] [--seed 7] [--json runs/registration.json]

For every task and level (`clean`, `camera`, `shifted`) it resets `--states` random states,
each an episode of its own look, renders the cell's camera frame and registers it:
- found: the share of frames registered (all four markers, or enough of them);
- homography error: the largest distance, over a grid on the canonical view's table, between
  where the estimated homography and the true one (from the drawn camera pose) send a frame
  point, in pixels of the canonical 256 frame; corner error: detected marker corners against
  their true places in the frame, frame pixels;
- time (p50, ms): a frame of a new look (the camera moved since the last frame: its markers
  looked for round where they were) and then another state seen by the same camera (tracked:
  refined from where they were, no detector);
- with the task's shipped model (`models/<task>`, or `--model`), per factor of the `camera`
  look (camera pose, lights, table, image pipeline, all of them): the L1 latent distance of
  the image to the clean render of the same physical state and the share of images the model
  knows,
  without registration (the moved camera's own view at the model's size) and with it, and
  with the warp alone (no colour step from the markers' cells), to see what that step does.
Prints markdown tables; `--json` keeps every figure.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.sim.appearance import AppearanceWorld
from services.sim.workcell import Pinhole, true_homography
from services.sim.worlds import make_world
from shared.appearance import APPEARANCES, Appearance, EpisodeRanges, ImageRanges
from shared.registration import Registration, RegistrationError, _apply

LEVELS = ("clean", "camera", "shifted")
_NONE = EpisodeRanges(
    light_turn_deg=0, light_intensity=0, ambient=0, camera_shift_m=0, camera_turn_deg=0,
    table_colour=0, table_texture=0,
)  # fmt: skip
_NO_IMAGE = ImageRanges(white_balance=0, exposure=0, noise_sigma=0, jpeg_quality=(100, 100))
_CAM = APPEARANCES["camera"]
FACTORS: dict[str, Appearance] = {
    "camera pose": Appearance("pose", replace(_NONE, camera_shift_m=0.005, camera_turn_deg=1.5)),
    "lights": Appearance(
        "lights", replace(_NONE, light_turn_deg=20, light_intensity=0.25, ambient=0.2)
    ),
    "table": Appearance("table", replace(_NONE, table_colour=0.05, table_texture=0.04)),
    "image pipeline": Appearance("pipeline", _NONE, _CAM.image),
    "all (camera)": _CAM,
}


def geometry(task: str, states: int, seed: int) -> dict[str, dict[str, float]]:
    """Found share, homography and corner errors, registration time, per level."""
    out = {}
    for level in LEVELS:
        world = make_world(task, 64, appearance=level)
        assert isinstance(world, AppearanceWorld)
        registration = Registration(world.task.workcell, 64)
        nominal = Pinhole.of(world.model, world.data, world.camera.camera)
        rng = np.random.default_rng([seed, LEVELS.index(level)])
        grid = np.stack(np.meshgrid(np.linspace(0, 255, 16), np.linspace(0, 255, 16)), -1)
        view = grid.reshape(-1, 2)
        found, errors, corner_errors, times, fixed, reasons = 0, [], [], [], [], []
        for _ in tqdm(range(states), desc=f"{task} {level}", leave=False):
            world.reset(world.task.sample_state(rng), rng)
            frame = world.frame()
            truth = true_homography(world.pinhole(), nominal)
            start = time.perf_counter()
            try:
                registered = registration.register(frame)
            except RegistrationError as exc:
                reasons.append(str(exc))
                continue
            times.append(time.perf_counter() - start)
            found += 1
            # where each estimate puts the canonical view's points, against the truth
            seen = _apply(np.linalg.inv(truth), view)
            errors.append(float(np.max(np.linalg.norm(_apply(registered.homography, seen) - view,
                                                      axis=1))))  # fmt: skip
            detected = registration.detect(frame)
            for ident, quad in detected.items():
                canonical = np.asarray(registration._corners[ident])
                corner_errors.extend(
                    np.linalg.norm(quad - _apply(np.linalg.inv(truth), canonical), axis=1).tolist()
                )
            # another state seen by the same camera: its markers are tracked from this frame
            world.world.reset(world.task.sample_state(rng), rng)
            again = world.frame()
            start = time.perf_counter()
            try:
                registration.register(again)
                fixed.append(time.perf_counter() - start)
            except RegistrationError as exc:
                reasons.append(str(exc))
        world.close()
        out[level] = {
            "frames": states,
            "found": found / states,
            "homography_p50_px": float(np.median(errors)) if errors else float("nan"),
            "homography_p99_px": float(np.quantile(errors, 0.99)) if errors else float("nan"),
            "homography_max_px": float(np.max(errors)) if errors else float("nan"),
            "corner_p50_px": float(np.median(corner_errors)) if corner_errors else float("nan"),
            "corner_max_px": float(np.max(corner_errors)) if corner_errors else float("nan"),
            "register_ms_p50": 1000 * float(np.median(times)) if times else float("nan"),
            "register_fixed_ms_p50": 1000 * float(np.median(fixed)) if fixed else float("nan"),
            "refused": reasons[:3],
        }
    return out


def factors(
    task: str, states: int, seed: int, model: Path | None = None
) -> dict[str, dict[str, float]]:
    """Per factor of the camera look: latent L1 to the clean render and share known, with the
    task's shipped model, without and with registration."""
    from services.encoder.checkpoint import load_vae
    from services.planner import knowing
    from services.planner.roadmap import Roadmap
    from services.planner.versions import roadmap_dir

    model = model or Path("models") / task
    vae, _ = load_vae(model / "vae")
    folder = roadmap_dir(model)
    roadmap = Roadmap.load(folder)
    calibration = knowing.load_calibration(folder, roadmap)
    out = {}
    for name, appearance in FACTORS.items():
        world = make_world(task, 64)
        looked = AppearanceWorld(world, appearance)
        registration = Registration(world.task.workcell, 64)
        geometric = Registration(world.task.workcell, 64, photometric=False)
        rng = np.random.default_rng([seed, 99])
        clean, before, after, warped = [], [], [], []
        refused = 0
        for _ in tqdm(range(states), desc=f"{task} {name}", leave=False):
            looked.reset(world.task.sample_state(rng), rng)
            clean.append(world.render())
            before.append(looked.render())
            frame = looked.frame()
            try:
                after.append(registration.register(frame).image)
                warped.append(geometric.register(frame).image)
            except RegistrationError:
                refused += 1
                after.append(np.zeros_like(clean[-1]))
                warped.append(after[-1])
        world.close()
        z_clean, _ = knowing.look(vae, np.stack(clean))
        row: dict[str, float] = {"unregistered_frames": refused}
        for label, images in (("before", before), ("after", after), ("geometric", warped)):
            z, errors = knowing.look(vae, np.stack(images))
            matches = knowing.match(roadmap, calibration, z, errors)
            row[f"{label}_l1"] = float(np.median(np.abs(z - z_clean).sum(1)))
            row[f"{label}_known"] = float(np.mean([m.known for m in matches]))
        out[name] = row
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=["box_stacking", "cloth_folding",
                                                       "tshirt_folding"])  # fmt: skip
    parser.add_argument("--states", type=int, default=100)
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--no-factors", action="store_true", help="skip the model part")
    parser.add_argument("--model", type=Path, help="for one task: another model than models/T")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    results: dict[str, dict] = {}
    print("| task | level | frames | registered | homography p50 / p99 / max (px at 256) | "
          "corner p50 / max (frame px) | ms: new look / fixed camera |")  # fmt: skip
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for task in args.tasks:
        results[task] = {"geometry": geometry(task, args.states, args.seed)}
        for level, r in results[task]["geometry"].items():
            print(f"| {task} | {level} | {r['frames']} | {100 * r['found']:.1f}% | "
                  f"{r['homography_p50_px']:.2f} / {r['homography_p99_px']:.2f} / "
                  f"{r['homography_max_px']:.2f} | {r['corner_p50_px']:.2f} / "
                  f"{r['corner_max_px']:.2f} | {r['register_ms_p50']:.1f} / "
                  f"{r['register_fixed_ms_p50']:.1f} |")  # fmt: skip
    if not args.no_factors:
        print("\n| task | factor | L1 to clean: unregistered -> registered (warp only) | known: "
              "unregistered -> registered (warp only) |")  # fmt: skip
        print("| --- | --- | --- | --- |")
        for task in args.tasks:
            if not (Path("models") / task / "vae").is_dir():
                continue
            model = args.model if args.model and len(args.tasks) == 1 else None
            results[task]["factors"] = factors(task, args.states, args.seed, model)
            for name, r in results[task]["factors"].items():
                print(
                    f"| {task} | {name} | {r['before_l1']:.2f} -> {r['after_l1']:.2f} "
                    f"({r['geometric_l1']:.2f}) | {100 * r['before_known']:.1f}% -> "
                    f"{100 * r['after_known']:.1f}% ({100 * r['geometric_known']:.1f}%) |"
                )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
