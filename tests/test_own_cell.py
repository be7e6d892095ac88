"""docs/own-cell.md run end to end on tiny data: a task known only from its recording, markers
laid out and printed, camera frames (drawn here: no simulator) registered on import, one
training command, a plan, and the plan's pixels on the table in millimetres."""

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from services.cli import main
from shared.workcell import BORDER_CELLS, Workcell, marker_cells

ROOT = Path(__file__).resolve().parents[1]
TASK = {
    "name": "towel_cell",
    "image_size": 32,
    "frame": 256,
    "action": [
        {"name": "pick.row", "range": [0, 255], "pixel": "row"},
        {"name": "pick.col", "range": [0, 255], "pixel": "col"},
        {"name": "release.row", "range": [0, 255], "pixel": "row"},
        {"name": "release.col", "range": [0, 255], "pixel": "col"},
    ],
}
# Four states: a red square at one of four places in the middle of the table, mm (x, y)
PLACES_MM = [(-110.0, 110.0), (110.0, 110.0), (110.0, -110.0), (-110.0, -110.0)]


def canonical(cell: Workcell, state: int, rng: np.random.Generator) -> np.ndarray:
    """The table seen from straight above in the 256 px canonical view: grey, the printed
    markers at their corners, the square where `state` puts it, a lamp's brightness."""
    view = np.full((256, 256, 3), 190, np.float64) * rng.uniform(0.85, 1.1)
    for marker in cell.markers:
        (x0, y0), (x1, y1) = marker.corners[0], marker.corners[2]
        margin = (x1 - x0) / (4 + 2 * BORDER_CELLS)
        view[round(y0 - margin) : round(y1 + margin), round(x0 - margin) : round(x1 + margin)] = 255
        side = (round(x1 - x0), round(y1 - y0))
        printed = marker_cells(marker.id).astype(np.uint8) * 255
        cells = cv2.resize(printed, side, interpolation=cv2.INTER_NEAREST)
        view[round(y0) : round(y0) + cells.shape[0], round(x0) : round(x0) + cells.shape[1]] = (
            cells[..., None]
        )
    row, col = (round(v) for v in cell.mm_to_pixel(*PLACES_MM[state]))
    view[row - 25 : row + 25, col - 25 : col + 25] = (200, 40, 40)
    noise = rng.normal(0, 3, view.shape)
    return np.clip(view + noise, 0, 255).astype(np.uint8)


def camera_frame(view: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """What a 320 x 280 camera above the table gives: the view turned, scaled and shifted a
    little (a camera nudged between looks)."""
    turn = np.radians(rng.uniform(-3, 3))
    scale = rng.uniform(1.0, 1.08)
    rotate = cv2.getRotationMatrix2D((128, 128), np.degrees(turn), scale)
    rotate[:, 2] += (160 - 128 + rng.uniform(-6, 6), 140 - 128 + rng.uniform(-6, 6))
    return cv2.warpAffine(view, rotate, (320, 280), borderValue=(120, 110, 100))


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    rec = tmp_path_factory.mktemp("cell") / "rec"
    (rec / "cam").mkdir(parents=True)
    (rec / "task.json").write_text(json.dumps(TASK))
    args = ["workcell", "layout", "--table-mm", "600", "600", "--marker-mm", "80"]
    assert main([*args, "--task-json", str(rec / "task.json")]) == 0
    return rec


@pytest.mark.timeout(1800)  # trains a model: a guard against hangs, not a deadline (2 min idle)
def test_the_page_from_sheet_to_plan(recorded, tmp_path):
    rec = recorded
    cell = Workcell.from_json(json.loads((rec / "task.json").read_text())["markers"])
    assert cell is not None and cell.ids == [0, 1, 2, 3]
    # 2. the sheet, tiled on A4 pages
    assert main(["workcell", "markers", "--task-json", str(rec / "task.json"),
                 "--out", str(tmp_path / "sheet.pdf")]) == 0  # fmt: skip
    assert (tmp_path / "sheet.pdf").read_bytes()[:5] == b"%PDF-"
    # 4. episodes: moves of the square and no-action pairs across looks
    rng = np.random.default_rng(0)
    lines, count = [], 0

    def shoot(state: int) -> str:
        nonlocal count
        count += 1
        name = f"cam/{count:04d}.png"
        Image.fromarray(camera_frame(canonical(cell, state, rng), rng)).save(rec / name)
        return name

    state = 0
    for step in range(40):
        first = shoot(state)
        if step % 3:
            target = int((state + 1 + rng.integers(3)) % 4)
            pick, release = (cell.mm_to_pixel(*PLACES_MM[s]) for s in (state, target))
            action = {"pick": {"row": round(pick[0]), "col": round(pick[1])},
                      "release": {"row": round(release[0]), "col": round(release[1])}}  # fmt: skip
        else:
            target, action = state, None
        lines.append({"image1": first, "image2": shoot(target), "action": action})
        state = target
    (rec / "pairs.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))
    # 3. a frame checked before recording
    view = tmp_path / "view.png"
    check = ["--task-json", str(rec / "task.json"), "--image", str(rec / "cam/0001.png")]
    assert main(["workcell", "check", *check, "--out", str(view)]) == 0
    assert Image.open(view).size == (256, 256)
    # 5. import (every frame registered) and one training command
    data = tmp_path / "data" / "towel"
    assert main(["data", "import", "--from", str(rec), "--out", str(data)]) == 0
    model = tmp_path / "runs" / "towel"
    assert main(["train", "model", "--data", str(data / "train"), "--out", str(model),
                 "--vae-steps", "150", "--apn-steps", "20", "--apn-restarts", "1",
                 "--min-samples", "1"]) == 0  # fmt: skip
    assert (model / "recipe.json").is_file()
    # a plan from a recorded frame (a whole camera frame) to itself
    # (in a process of its own, as a user runs it: this one has declared the task from
    # task.json's markers, the model carries the levels measured on import)
    frame = rec / lines[0]["image1"]
    out = tmp_path / "plans"
    ends = ["--start-image", str(frame), "--goal-image", str(frame), "--out", str(out)]
    command = [sys.executable, "-m", "services.cli", "plan", "--model", str(model), *ends]
    done = subprocess.run(command, capture_output=True, text=True, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-2000:]
    assert any(out.iterdir())
    # 4. actions in table millimetres: a recorded pick is where the square lay
    for line in lines:
        if line["action"] is None:
            continue
        pick = line["action"]["pick"]
        mm = cell.pixel_to_mm(pick["row"], pick["col"])
        assert min(np.hypot(mm[0] - px, mm[1] - py) for px, py in PLACES_MM) < 2.0
