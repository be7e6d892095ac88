"""Table I against the camera's rotation, with and without registration to the table frame.

Usage:
    .venv/bin/python benchmarks/bench_rotation.py [--model models/box_stacking]
        [--turns 0 1.5 3 5 10] [--heights 0.1 0.2] [--states 400] [--pairs 1000] [--seed 17]
        [--json runs/rotation.json] [--figure docs/images/rotation_box.png]

For each turn (degrees of the camera's roll, pitch and yaw, each drawn within +-turn; 1.5 is
the `camera` level's, 5 robosuite's default) every other part of the `camera` look stays at
its level; with `--heights`, also rows with the camera's height above the table drawn within
+-that share (0.2: +-20%), turns at the `camera` level. `--states` random states are each
reset under a fresh draw and seen two ways:
- without registration: the moved camera's own view at the model's size, as a camera bolted
  where the canonical one was would give it;
- with registration: the cell's whole frame, registered to the table frame from the markers.
Each set is encoded by the model and planned over `--pairs` random pairs (Table I as `lsr eval
vfm` computes it, with the model's calibration); an image the model does not know, or whose
markers are not found, gets no plan, so its pairs count as failed: All and Any here are over
all pairs, refusals included. Prints a markdown table; `--json` keeps every figure.
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

from services.encoder.checkpoint import encode_images
from services.planner import knowing
from services.planner.build import load_model
from services.planner.evaluate import evaluate_plans, sample_test_pairs
from services.planner.versions import roadmap_dir
from services.sim.appearance import AppearanceWorld
from services.sim.workcell import Observer
from services.sim.worlds import make_world
from shared.appearance import APPEARANCES, Appearance
from shared.registration import RegistrationError


def look_at(camera_turn_deg: float, camera_height: float = 0.0) -> Appearance:
    camera = APPEARANCES["camera"]
    assert camera.episode is not None
    episode = replace(camera.episode, camera_turn_deg=camera_turn_deg, camera_height=camera_height)
    name = f"turn {camera_turn_deg:g}" + (
        f", height +-{camera_height:.0%}" if camera_height else ""
    )
    return replace(camera, name=name, episode=episode)


def images_at(
    task: str, size: int, turn: float, states: int, seed: int, height: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """States, unregistered views, registered frames and whether each frame registered."""
    world = make_world(task, size, appearance="camera")
    assert isinstance(world, AppearanceWorld)
    world.use(look_at(turn, height))
    observer = Observer(world)
    heights = [int(height * 100)] if height else []  # the turns' draws stay as they were
    rng = np.random.default_rng([seed, int(turn * 100), *heights])
    rows, plain, registered, found = [], [], [], []
    try:
        for _ in tqdm(range(states), desc=f"turn {turn:g}", leave=False):
            state = world.task.sample_state(rng)
            world.reset(state, rng)
            rows.append(world.task.state_to_array(state))
            plain.append(world.render())
            try:
                registered.append(observer.see())
                found.append(True)
            except RegistrationError:
                registered.append(np.zeros_like(plain[-1]))
                found.append(False)
    finally:
        world.close()
    return np.stack(rows), np.stack(plain), np.stack(registered), np.array(found)


def table1(model: Path, states: np.ndarray, images: np.ndarray, usable: np.ndarray,
           pairs: int, seed: int) -> dict[str, float]:  # fmt: skip
    """All / Any / Trans over all pairs (a pair with an end refused fails) and known share."""
    vae, config, roadmap, labels = load_model(model)
    calibration = knowing.load_calibration(roadmap_dir(model), roadmap)
    z, _ = encode_images(vae, images)
    errors = knowing.reconstruction_errors(vae, images, z)
    known = np.array([m.known for m in knowing.match(roadmap, calibration, z, errors)]) & usable
    test_pairs = sample_test_pairs(len(images), pairs, seed)
    both = known[test_pairs].all(1)
    row = {"known": 100.0 * float(known.mean()), "pairs_known": 100.0 * float(both.mean())}
    if both.any():
        kept = evaluate_plans(
            config["dataset"]["task"], roadmap, labels, z, states, test_pairs[both], 1000,
            calibration=calibration,
        )  # fmt: skip
        share = float(both.mean())
        row.update(all=kept["all"] * share, any=kept["any"] * share, trans=kept["trans"])
    else:
        row.update(all=0.0, any=0.0, trans=0.0)
    return row


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, default=Path("models/box_stacking"))
    parser.add_argument("--turns", type=float, nargs="+", default=[0, 1.5, 3, 5, 10])
    parser.add_argument(
        "--heights",
        type=float,
        nargs="*",
        default=[],
        help="also rows with the camera's height drawn within +-this share (turns at `camera`)",
    )
    parser.add_argument("--states", type=int, default=400)
    parser.add_argument("--pairs", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=17)
    parser.add_argument("--json", type=Path)
    parser.add_argument("--figure", type=Path)
    args = parser.parse_args()
    _, config, _, _ = load_model(args.model)
    task, size = config["dataset"]["task"], int(config["model"]["image_size"])
    results = []
    camera_turn = APPEARANCES["camera"].episode.camera_turn_deg  # type: ignore[union-attr]
    rows = [(turn, 0.0) for turn in args.turns] + [(camera_turn, h) for h in args.heights]
    for turn, height in rows:
        started = time.perf_counter()
        states, plain, registered, found = images_at(
            task, size, turn, args.states, args.seed, height
        )
        everything = np.ones(len(plain), bool)
        results.append(
            {
                "turn_deg": turn,
                "height": height,
                "registered_frames": 100.0 * float(found.mean()),
                "without": table1(args.model, states, plain, everything, args.pairs, args.seed),
                "with": table1(args.model, states, registered, found, args.pairs, args.seed),
                "seconds": round(time.perf_counter() - started, 1),
            }
        )
    print(
        f"model {args.model} ({task}), {args.states} states, {args.pairs} pairs, seed {args.seed}"
    )
    print("| turn (deg) | height | frames registered | without: All / Any / Trans, known | "
          "with: All / Any / Trans, known |")  # fmt: skip
    print("| --- | --- | --- | --- | --- |")
    for r in results:
        cells = [
            f"{r[k]['all']:.1f} / {r[k]['any']:.1f} / {r[k]['trans']:.1f}, {r[k]['known']:.1f}%"
            for k in ("without", "with")
        ]
        height = f"+-{r['height']:.0%}" if r["height"] else "-"
        print(
            f"| {r['turn_deg']:g} | {height} | {r['registered_frames']:.1f}% | {cells[0]} "
            f"| {cells[1]} |"
        )
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"args": vars(args) | {"model": str(args.model),
                             "json": str(args.json), "figure": str(args.figure)},
                             "results": results}, indent=2))  # fmt: skip
    if args.figure:
        plot(results, args.figure, f"{args.model} ({task})")
    return 0


def plot(results: list[dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    results = [r for r in results if not r["height"]]  # the turns
    turns = [r["turn_deg"] for r in results]
    fig, ax = plt.subplots(figsize=(5.5, 3.4), dpi=120)
    for key, style in (("with", "o-"), ("without", "s--")):
        ax.plot(turns, [r[key]["all"] for r in results], style, label=f"{key} registration")
    ax.set_xlabel("camera rotation, each axis (degrees)")
    ax.set_ylabel("Table I All (%)")
    ax.set_ylim(-2, 102)
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)


if __name__ == "__main__":
    raise SystemExit(main())
