"""A recorded dataset as a user would hand it over: PNG files, task.json and pairs.jsonl."""

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

# Four "states": a background colour and a square in one quadrant, so that even a briefly
# trained encoder tells them apart. An action moves the square from one quadrant to another.
COLOURS = [(200, 60, 60), (60, 200, 60), (60, 60, 200), (200, 200, 60)]
CENTRES = [(12, 12), (12, 36), (36, 12), (36, 36)]  # (row, col) in the 48 px recording


def draw(state: int, rng: np.random.Generator, size: tuple[int, int] = (48, 48)) -> np.ndarray:
    """A 48 x 48 view of `state` (or wider: extra columns on both sides, cropped on import)."""
    h, w = size
    image = np.zeros((h, w, 3), np.uint8) + np.array(COLOURS[state], np.uint8)
    r, c = CENTRES[state]
    c += (w - 48) // 2
    image[r - 6 : r + 6, c - 6 : c + 6] = 255
    noise = rng.integers(-8, 9, size=image.shape)
    return np.clip(image.astype(int) + noise, 0, 255).astype(np.uint8)


TASK = {
    "name": "square_moving",
    "image_size": 32,
    "frame": 48,
    "action": [
        {"name": "pick.row", "range": [0, 47], "pixel": "row"},
        {"name": "pick.col", "range": [0, 47], "pixel": "col"},
        {"name": "release.row", "range": [0, 47], "pixel": "row"},
        {"name": "release.col", "range": [0, 47], "pixel": "col"},
        {"name": "grip", "categories": ["soft", "firm"]},
    ],
    "settings": {"w_eps": 1.0, "min_samples": 1},
}


def write_recorded(
    root: Path, episodes: int = 12, length: int = 6, seed: int = 0, wide_every: int = 5
) -> Path:
    """`episodes` walks of `length` pairs over the four states, half of them actions; every
    `wide_every`-th image is 64 x 48 (a wider camera), which the import crops and resizes."""
    rng = np.random.default_rng(seed)
    (root / "img" / "sub").mkdir(parents=True, exist_ok=True)
    (root / "task.json").write_text(json.dumps(TASK))
    lines, count = [], 0

    def save(state: int) -> str:
        nonlocal count
        count += 1
        size = (48, 64) if count % wide_every == 0 else (48, 48)
        folder = "img/sub" if count % 2 else "img"
        name = f"{folder}/frame{count:04d}.png"
        Image.fromarray(draw(state, rng, size)).save(root / name)
        return name

    for episode in range(episodes):
        state = int(rng.integers(4))
        for step in range(length):
            first = save(state)
            if step % 2 == 0:
                target = int((state + 1 + rng.integers(3)) % 4)
                (pr, pc), (rr, rc) = CENTRES[state], CENTRES[target]
                action = {
                    "pick": {"row": pr, "col": pc},
                    "release": {"row": rr, "col": rc},
                    "grip": ["soft", "firm"][step % 4 // 2],
                }
            else:
                target, action = state, None
            second = save(target)
            lines.append(
                {"image1": first, "image2": second, "action": action, "episode": f"ep{episode}"}
            )
            state = target
    (root / "pairs.jsonl").write_text("".join(json.dumps(line) + "\n" for line in lines))
    return root


@pytest.fixture
def recorded(tmp_path) -> Path:
    return write_recorded(tmp_path / "recorded")


@pytest.fixture(scope="session")
def write_recorded_fn():
    return write_recorded
