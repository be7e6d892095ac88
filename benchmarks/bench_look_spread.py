"""Which part of a camera's look moves a model's latents most: one factor at a time.

Usage:
    .venv/bin/python benchmarks/bench_look_spread.py --vae runs/tshirt_2566/vae_l1/vae \
        [--appearance camera] [--states 8] [--draws 8] [--seed 0]

Resets each of a few states (drawn with the seed; for a task with hidden parts, only states
that show everything) at one pose and renders it at the clean look, then with one factor of
the appearance level drawn at a time, everything else at its default: the lights (direction,
intensity, ambient), the camera pose, the table (colour, texture), the image pipeline (white
balance, exposure, noise, JPEG), and all of them together as in the data. Prints the mean latent
distance (the VAE's roadmap metric) from the clean render for each, beside what a fresh pose of
the same state moves (another reset) and the distance to another state at the same pose: a
factor that moves latents as far as a change of state is one the roadmap cannot look through.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.encoder.checkpoint import encode_images, load_vae
from services.planner.build import default_metric
from services.planner.regions import metric_p
from services.sim.appearance import SceneModder, post_process
from services.sim.worlds import make_world
from shared.appearance import EpisodeSample, get_appearance
from shared.tasks import get_task

DEFAULT = EpisodeSample(
    light_tilt=0.0,
    light_azimuth=0.0,
    light_gain=1.0,
    ambient_gain=1.0,
    camera_shift=(0.0, 0.0, 0.0),
    camera_turn=(0.0, 0.0, 0.0),
    table_gain=(1.0, 1.0, 1.0),
    table_texture=0.0,
    texture_seed=0,
)
FACTORS = {
    "lights": ("light_tilt", "light_azimuth", "light_gain", "ambient_gain"),
    "camera pose": ("camera_shift", "camera_turn"),
    "table": ("table_gain", "table_texture", "texture_seed"),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vae", type=Path, required=True)
    parser.add_argument("--appearance", default="camera")
    parser.add_argument("--states", type=int, default=8)
    parser.add_argument("--draws", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    vae, config = load_vae(args.vae)
    task = get_task(config["dataset"]["task"])
    p = metric_p(default_metric(config))
    level = get_appearance(args.appearance)
    rng = np.random.default_rng(args.seed)
    every = [s for s in task.all_states() if not task.hidden(s)]
    states = [every[i] for i in rng.permutation(len(every))[: args.states]]
    world = make_world(task.name, vae.config.image_size)
    modder = SceneModder(world)

    def encode(images: list[np.ndarray]) -> np.ndarray:
        return encode_images(vae, np.stack(images))[0]

    moved: dict[str, list[float]] = {}
    for k, state in enumerate(states):
        world.reset(state, np.random.default_rng([args.seed, k]))
        clean = encode([modder.render(DEFAULT)])[0]
        renders: dict[str, list[np.ndarray]] = {}
        for _ in range(args.draws):
            episode = level.draw_episode(rng)
            assert episode is not None, f"{args.appearance} draws no episode look"
            for name, fields in FACTORS.items():
                one = dataclasses.replace(DEFAULT, **{f: getattr(episode, f) for f in fields})
                renders.setdefault(name, []).append(modder.render(one))
            image = level.draw_image(rng)
            plain = modder.render(DEFAULT)
            renders.setdefault("image pipeline", []).append(
                plain if image is None else post_process(plain, image)
            )
            whole = modder.render(episode)
            renders.setdefault("all together", []).append(
                whole if image is None else post_process(whole, image)
            )
        for name, images in renders.items():
            gaps = np.linalg.norm(encode(images) - clean, ord=p, axis=1)
            moved.setdefault(name, []).extend(gaps.tolist())
        poses = []
        for d in range(args.draws):
            world.reset(state, np.random.default_rng([args.seed, k, d + 1]))
            poses.append(modder.render(DEFAULT))
        moved.setdefault("a fresh pose (clean look)", []).extend(
            np.linalg.norm(encode(poses) - clean, ord=p, axis=1).tolist()
        )
        others = []
        for other in states:
            if other != state:
                world.reset(other, np.random.default_rng([args.seed, k]))
                others.append(modder.render(DEFAULT))
        moved.setdefault("another state, same pose seed", []).extend(
            np.linalg.norm(encode(others) - clean, ord=p, axis=1).tolist()
        )
    world.close()
    print(f"{args.vae}: {len(states)} states, {args.draws} draws each, {args.appearance}\n")
    print("| what changes | latent distance from the clean render: mean | 90% |")
    print("| --- | --- | --- |")
    for name, gaps in moved.items():
        print(f"| {name} | {np.mean(gaps):.2f} | {np.quantile(gaps, 0.9):.2f} |")


if __name__ == "__main__":
    main()
