"""Knowing an image (issue 21): how many unseen test images a model knows, and how many images
of each foreign kind it refuses, with the scores' distributions as a figure.

Usage:
    .venv/bin/python benchmarks/bench_knowing.py --model models/box_stacking \
        --test data/box_stacking/test --foreign data/cloth_folding/test \
        [--per-kind 500] [--seed 0] [--json runs/knowing/box_stacking.json]
    .venv/bin/python benchmarks/bench_knowing.py --figure docs/images/knowing_scores.png \
        runs/knowing/*.json

Foreign kinds are made from the model's own test images (uniform noise, solid frames, colour
inversion, rotation by 180 degrees, a shift by a third of the frame rolled round or padded with
the edge, half the frame covered, under- and over-exposure), taken from other tasks' datasets
(`--foreign`, resized to the model's size where they differ) and, for box stacking, rendered
from modified scenes: a box missing, a fifth box of a new colour, a second red box. Prints one
markdown table (kind, images, known or refused share, lowest and median score) and writes every
score to the JSON file, from which `--figure` draws.

With `--frames N` (a task with markers), the same transforms are also applied to N cell camera
frames of random states (at the model's training look) before they are registered to the table
frame, as a camera would give them: a frame whose markers are not found is refused before the
model (score REFUSED), and for every frame the model knows it says whether its nearest roadmap
node stands for the frame's true state (a camera turned upside down registers back upright).
    .venv/bin/python benchmarks/bench_knowing.py --model models/box_stacking \
        --test data/box_camera/test_camera --frames 300 --json runs/knowing/box_frames.json

With `--show KIND --figure OUT`, the images of one transform that the model knows, to look at
rather than count: `--per-kind` test images drawn with `--seed`, transformed, and the first 12
known drawn in rows (the test image, the transformed one, the decoded node it is known at).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.planner import knowing
from services.planner.build import load_model
from services.planner.eval_vfm import load_test_images
from services.planner.plan import VisualPlanner
from services.planner.versions import roadmap_dir
from shared.appearance import manifest_appearance
from shared.dataset import load_dataset

TERMS = ("distance", *knowing.ERRORS)
Kind = Callable[[np.ndarray, np.random.Generator], np.ndarray]


def _shift(images: np.ndarray, rng: np.random.Generator, roll: bool) -> np.ndarray:
    """Each image moved by a third of the frame along a drawn axis and direction."""
    out = np.empty_like(images)
    third = images.shape[1] // 3
    for k, image in enumerate(images):
        axis, sign = int(rng.integers(2)), int(rng.choice([-1, 1]))
        moved = np.roll(image, sign * third, axis=axis)
        if not roll:  # what enters the frame repeats the edge it came from
            index = [slice(None)] * 3
            edge = [slice(None)] * 3
            index[axis] = slice(0, third) if sign > 0 else slice(-third, None)
            edge[axis] = slice(0, 1) if sign > 0 else slice(-1, None)
            moved[tuple(index)] = image[tuple(edge)]
        out[k] = moved
    return out


def _half_covered(images: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A random half (top, bottom, left or right) covered by one drawn colour."""
    out = images.copy()
    half = images.shape[1] // 2
    for image in out:
        side = int(rng.integers(4))
        cover = rng.integers(0, 256, 3, dtype=np.uint8)
        area = [slice(None, half), slice(half, None)][side % 2]
        if side < 2:
            image[area] = cover
        else:
            image[:, area] = cover
    return out


def _exposed(gain: float, offset: float) -> Kind:
    def expose(images: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        return np.clip(images.astype(np.float32) * gain + offset, 0, 255).astype(np.uint8)

    return expose


TRANSFORMS: dict[str, Kind] = {
    "uniform noise": lambda x, rng: rng.integers(0, 256, x.shape, dtype=np.uint8),
    "solid frame": lambda x, rng: np.broadcast_to(
        rng.integers(0, 256, (len(x), 1, 1, 3), dtype=np.uint8), x.shape
    ).copy(),
    "colour inversion": lambda x, rng: 255 - x,
    "rotation 180": lambda x, rng: x[:, ::-1, ::-1].copy(),
    "third shift, rolled": lambda x, rng: _shift(x, rng, roll=True),
    "third shift, edge-padded": lambda x, rng: _shift(x, rng, roll=False),
    "half covered": _half_covered,
    "under-exposed (x0.2)": _exposed(0.2, 0.0),
    "over-exposed (x2.5 + 60)": _exposed(2.5, 60.0),
}


def _resized(images: np.ndarray, size: int) -> np.ndarray:
    if images.shape[1] == size:
        return images
    return np.stack(
        [np.asarray(Image.fromarray(i).resize((size, size), Image.BILINEAR)) for i in images]
    )


def _box_scenes(
    boxes: tuple[str, ...], count: int, size: int, rng: np.random.Generator
) -> np.ndarray:
    """Renders of drawn states of a box-stacking scene with these boxes (a modified scene)."""
    from services.sim.box_stacking.scene import BOX_LOOKS
    from services.sim.box_stacking.world import BoxStackingWorld
    from shared.tasks.box_stacking import BoxStacking, BoxStackingConfig

    purple = 'builtin="flat" rgb1=".55 .2 .7" rgb2=".55 .2 .7"'
    looks = {**BOX_LOOKS, "purple": purple, "red2": BOX_LOOKS["red"]}
    task = BoxStacking(BoxStackingConfig(boxes=boxes))
    with BoxStackingWorld(task, size, box_looks=looks) as world:
        images = []
        for _ in range(count):
            world.reset(task.sample_state(rng), rng)
            images.append(world.render())
    return np.stack(images)


def foreign_kinds(
    task: str, test: np.ndarray, others: list[Path], per_kind: int, rng: np.random.Generator
) -> dict[str, np.ndarray]:
    kinds = {}
    for name, transform in TRANSFORMS.items():
        kinds[name] = transform(test[rng.choice(len(test), per_kind, replace=False)], rng)
    size = test.shape[1]
    for other in others:
        data = load_dataset(other)
        images = np.concatenate([data.image1, data.image2])
        picked = images[rng.choice(len(images), min(per_kind, len(images)), replace=False)]
        look = manifest_appearance(data.manifest)
        label = f"{data.task} images" + ("" if look == "clean" else f" ({look})")
        kinds[label] = _resized(picked, size)
    if task == "box_stacking":
        four = ("red", "green", "blue", "yellow")
        missing = [tuple(b for b in four if b != gone) for gone in four]
        share = -(-per_kind // len(missing))
        kinds["a box missing"] = np.concatenate(
            [_box_scenes(boxes, share, size, rng) for boxes in missing]
        )[:per_kind]
        kinds["a fifth box (purple)"] = _box_scenes((*four, "purple"), per_kind, size, rng)
        kinds["a second red box"] = _box_scenes((*four, "red2"), per_kind, size, rng)
    return kinds


REFUSED = 1e9  # the score of a frame whose markers were not found (no model saw it)


def frame_kinds(
    task: str, size: int, look: str, count: int, rng: np.random.Generator
) -> tuple[dict[str, tuple[np.ndarray, list[str | None]]], np.ndarray]:
    """Each transform applied to `count` cell frames of random states, then registered: per
    kind, the images the model is given and why a frame was refused; and the true states."""
    from services.sim.worlds import make_world
    from shared.registration import Registration, to_table_frame
    from shared.tasks import get_task

    logic = get_task(task)
    registration = Registration(logic.workcell, size)
    frames, states = [], []
    with make_world(task, size, appearance=look) as world:
        for _ in range(count):
            state = logic.sample_state(rng)
            world.reset(state, rng)
            frames.append(world.frame())
            states.append(logic.state_to_array(state))
    frames_array = np.stack(frames)
    kinds = {"frame as it is": to_table_frame(registration, frames_array)}
    for name, transform in TRANSFORMS.items():
        kinds[f"frame, {name}"] = to_table_frame(registration, transform(frames_array, rng))
    return kinds, np.stack(states)


def scores(planner: VisualPlanner, images: np.ndarray) -> np.ndarray:
    """(N, 4): each term over its threshold (TERMS)."""
    assert planner.calibration is not None
    z, errors = planner.look(images)
    return knowing.ratios(planner.roadmap, planner.calibration, z, errors)[1]


def _planner(model: Path) -> tuple[VisualPlanner, dict]:
    """The model's planner with its calibration, and its VAE's config."""
    vae, vae_config, roadmap, _ = load_model(model)
    calibration = knowing.load_calibration(roadmap_dir(model), roadmap)
    return VisualPlanner(vae, roadmap, calibration), vae_config


def run(args: argparse.Namespace) -> dict:
    started = time.perf_counter()
    planner, vae_config = _planner(args.model)
    calibration = planner.calibration
    assert calibration is not None  # load_calibration raised where there is none
    test, _, task = load_test_images(args.test)
    rng = np.random.default_rng(args.seed)
    result = {
        "model": str(args.model),
        "task": task,
        "test": str(args.test),
        "appearance": vae_config["dataset"].get("appearance", "clean"),
        "seed": args.seed,
        "calibration": calibration.to_json(),
        "terms": list(TERMS),
        "kinds": {"unseen test images": scores(planner, test).tolist()},
    }
    for name, images in foreign_kinds(task, test, args.foreign, args.per_kind, rng).items():
        result["kinds"][name] = scores(planner, images).tolist()
    if args.frames:
        look = vae_config["dataset"].get("appearance", "clean")
        kinds, states = frame_kinds(task, test.shape[1], look, args.frames, rng)
        labels = load_model(args.model)[3]
        result["frames"] = {}
        for name, (images, refused) in kinds.items():
            terms = scores(planner, images)
            terms[[why is not None for why in refused]] = REFUSED
            z, _ = planner.look(images)
            nodes = np.asarray(planner.roadmap.nearest_node(z))
            known = terms.max(1) <= 1
            right = (labels.states[nodes] == states).reshape(len(states), -1).all(1)
            result["kinds"][name] = terms.tolist()
            result["frames"][name] = {
                "registered": 100.0 * float(np.mean([why is None for why in refused])),
                "known": 100.0 * float(known.mean()),
                "known_at_the_right_node": 100.0
                * float((known & right).sum() / max(1, known.sum())),
            }
    result["seconds"] = time.perf_counter() - started
    return result


def show_known(args: argparse.Namespace, count: int = 12) -> str:
    """The first `count` images of the transform `args.show` the model knows, drawn in rows
    (test image, transformed image, the decoded node it is known at) into `args.figure`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from services.encoder.checkpoint import decode_latents

    if args.show not in TRANSFORMS:
        raise SystemExit(f"--show: one of {', '.join(TRANSFORMS)}, got {args.show!r}")
    planner, _ = _planner(args.model)
    roadmap, calibration = planner.roadmap, planner.calibration
    assert calibration is not None
    test = load_test_images(args.test)[0]
    rng = np.random.default_rng(args.seed)
    drawn = test[rng.choice(len(test), args.per_kind, replace=False)]
    moved = TRANSFORMS[args.show](drawn, rng)
    z, errors = planner.look(moved)
    nodes, terms = knowing.ratios(roadmap, calibration, z, errors)
    known = np.flatnonzero(terms.max(1) <= 1)[:count]
    if not len(known):
        return f"{args.show}: none of {len(moved)} known"
    decoded = decode_latents(planner.vae, roadmap.nodes[nodes[known]].astype(np.float32))
    fig, axes = plt.subplots(len(known), 3, figsize=(4.2, 1.45 * len(known)), squeeze=False)
    titles = ("test image", args.show, "node known at")
    for row, (k, node_image) in enumerate(zip(known, decoded, strict=True)):
        for col, image in enumerate((drawn[k], moved[k], node_image)):
            axes[row][col].imshow(image)
            axes[row][col].axis("off")
            if row == 0:
                axes[row][col].set_title(titles[col], fontsize=7)
    fig.tight_layout()
    fig.savefig(args.figure, dpi=100)
    everyone = int((terms.max(1) <= 1).sum())
    return f"{args.show}: {everyone} of {len(moved)} known; the first {len(known)} in {args.figure}"


def table(result: dict) -> str:
    lines = [
        f"{result['model']} ({result['task']}, test {result['test']}):\n",
        "| images | n | known | refused | lowest score | median score | refused by each term: "
        + ", ".join(TERMS)
        + " |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for name, values in result["kinds"].items():
        terms = np.asarray(values)
        s = terms.max(1)
        known = 100 * float((s <= 1).mean())
        each = " / ".join(f"{100 * float(x):.0f}" for x in (terms > 1).mean(0))
        lines.append(
            f"| {name} | {len(s)} | {known:.2f}% | {100 - known:.2f}% | {s.min():.2f} | "
            f"{np.median(s):.2f} | {each} |"
        )
    return "\n".join(lines)


def figure(paths: list[Path], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    results = [json.loads(p.read_text()) for p in paths]
    kinds = list(dict.fromkeys(name for r in results for name in r["kinds"]))
    fig, axes = plt.subplots(1, len(results), figsize=(5.2 * len(results), 0.38 * len(kinds) + 1.4),
                             sharey=True, squeeze=False)  # fmt: skip
    for ax, r in zip(axes[0], results, strict=True):
        for y, name in enumerate(kinds):
            if name not in r["kinds"]:
                continue
            s = np.clip(np.asarray(r["kinds"][name]).max(1), 1e-2, 1e4)
            jitter = np.random.default_rng(y).uniform(-0.3, 0.3, len(s))
            colour = "tab:green" if y == 0 else "tab:red"
            ax.scatter(s, y + jitter, s=2, alpha=0.35, color=colour, linewidths=0)
        ax.axvline(1.0, color="k", lw=1, ls="--")
        ax.set_xscale("log")
        ax.set_title(f"{r['model']} ({r['appearance']})", fontsize=10)
        ax.set_xlabel("score (known while <= 1)")
    axes[0][0].set_yticks(range(len(kinds)), kinds, fontsize=8)
    axes[0][0].invert_yaxis()
    fig.tight_layout()
    fig.savefig(out, dpi=90)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path)
    parser.add_argument("--test", type=Path)
    parser.add_argument("--foreign", type=Path, nargs="*", default=[])
    parser.add_argument("--per-kind", type=int, default=500)
    parser.add_argument("--frames", type=int, default=0, help="cell frames per transform")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path)
    parser.add_argument("--figure", type=Path, help="draw from the JSON files given after it")
    parser.add_argument("--show", help="a transform whose known images --figure draws")
    parser.add_argument("results", type=Path, nargs="*")
    args = parser.parse_args()
    if args.show:
        if args.model is None or args.test is None or args.figure is None:
            parser.error("--show needs --model, --test and --figure")
        print(show_known(args))
        return
    if args.figure:
        figure(args.results, args.figure)
        print(f"wrote {args.figure}")
        return
    if args.model is None or args.test is None:
        parser.error("--model and --test are needed (or --figure with JSON files)")
    result = run(args)
    print(table(result))
    if result.get("frames"):
        print(
            "\n| frames | registered | known | known at the right node |\n| --- | --- | --- | --- |"
        )
        for name, row in result["frames"].items():
            print(f"| {name} | {row['registered']:.1f}% | {row['known']:.1f}% | "
                  f"{row['known_at_the_right_node']:.1f}% |")  # fmt: skip
    print(f"\n{result['seconds']:.0f} s")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result) + "\n")


if __name__ == "__main__":
    main()
