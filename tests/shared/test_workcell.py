"""A cell of your own: corner markers for a rectangle of table, the pixels of its registered
view in table millimetres, and its `"markers"` section through task.json and the import.

No simulator: the camera frames are drawn here, a top-down look at a table with the printed
markers on it, through a known camera homography."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from PIL import Image

from services.cli import main
from services.data.importer import ImportConfig, import_dataset, read_declaration
from shared.dataset import load_dataset
from shared.registration import Registration
from shared.tasks import get_task
from shared.workcell import Workcell, WorkcellError, marker_cells, rectangle_layout

TASK = {
    "name": "towel",
    "image_size": 64,
    "frame": 256,
    "action": [
        {"name": "pick.row", "range": [0, 255], "pixel": "row"},
        {"name": "pick.col", "range": [0, 255], "pixel": "col"},
    ],
}
TABLE = (600.0, 450.0)
SPOT = (120.0, -80.0)  # a red dot on the table, mm


def test_the_rectangle_layout_puts_a_marker_inside_each_corner():
    workcell = rectangle_layout(TABLE, 80.0, inset_mm=10.0)
    assert workcell.ids == [0, 1, 2, 3] and workcell.min_markers == 3
    centres = [m.centre_mm for m in workcell.markers]
    assert centres == [(-250.0, 175.0), (250.0, 175.0), (250.0, -175.0), (-250.0, -175.0)]
    # a top-down view of the rectangle: 256 / 600 pixels a mm, the centre at the view's centre
    ppm = 256 / 600
    far_left = workcell.markers[0].corners[0]  # the printed top-left corner of marker 0
    assert far_left == pytest.approx((127.5 - 290 * ppm, 127.5 - 215 * ppm), abs=1e-3)
    assert rectangle_layout(TABLE, 60.0).markers[0].centre_mm == (-260.0, 185.0)  # inset 10
    with pytest.raises(WorkcellError, match="do not fit"):
        rectangle_layout(TABLE, 220.0)


@pytest.mark.parametrize("task", ["box_stacking", "cloth_folding", "rope_box", "tshirt_folding"])
def test_pixels_and_millimetres_round_trip_and_fit_every_marker_s_corners(task):
    workcell = get_task(task).workcell
    for row, col in [(0, 0), (128, 40), (255, 255), (17.5, 230.25)]:
        x, y = workcell.pixel_to_mm(row, col)
        assert workcell.mm_to_pixel(x, y) == pytest.approx((row, col), abs=1e-6)
        # an action in a 64 px frame names the same table point as in the 256 frame
        assert workcell.pixel_to_mm((row + 0.5) / 4 - 0.5, (col + 0.5) / 4 - 0.5, frame=64) == (
            pytest.approx((x, y), abs=1e-6)
        )
    # every marker's printed corners land where the canonical view sees them (sub-pixel: the
    # built-in corners are calibrated from a render, not computed)
    for marker, corners in zip(workcell.markers, workcell.table_corners_mm(), strict=True):
        for (x, y), (u, v) in zip(corners, marker.corners, strict=True):
            assert workcell.mm_to_pixel(x, y) == pytest.approx((v, u), abs=0.8)


def test_the_rectangle_s_pixels_are_its_millimetres_scaled():
    workcell = rectangle_layout(TABLE, 80.0)
    ppm = 256 / 600
    # the centre of pixel (row, col) is at ((col + 0.5) / ppm - 300, 300 - (row + 0.5) / ppm)
    for row, col in [(0, 0), (127, 128), (255, 10)]:
        x, y = workcell.pixel_to_mm(row, col)
        assert (x, y) == pytest.approx(((col + 0.5) / ppm - 300, 300 - (row + 0.5) / ppm), abs=0.01)
    no_places = Workcell.from_json({"markers": [{"id": 0, "corners": [[0, 0]] * 4}]})
    with pytest.raises(WorkcellError, match="centre_mm and side_mm"):
        no_places.pixel_to_mm(0, 0)


def table_frame(workcell: Workcell, turn_deg: float = 2.0, shift=(9.0, -6.0)) -> np.ndarray:
    """A camera frame (900 x 700 px, about 1.2 px a mm) looking down on the table, turned and
    shifted a little: grey table, white paper round each marker, a red dot at SPOT."""
    ppm = 2.0  # the drawing's pixels a mm, before the camera sees it
    width, height = TABLE
    canvas = np.full((int(height * ppm), int(width * ppm), 3), 170, np.uint8)

    def px(x: float, y: float) -> tuple[float, float]:
        return (x + width / 2) * ppm, (height / 2 - y) * ppm

    for marker in workcell.markers:
        cells = marker_cells(marker.id)
        n = cells.shape[0]
        cell = marker.side_mm / n
        x0, y0 = px(
            marker.centre_mm[0] - marker.side_mm / 2, marker.centre_mm[1] + marker.side_mm / 2
        )
        pad = cell * ppm
        canvas[int(y0 - pad) : int(y0 + (marker.side_mm + cell) * ppm),
               int(x0 - pad) : int(x0 + (marker.side_mm + cell) * ppm)] = 250  # fmt: skip
        for r in range(n):
            for c in range(n):
                if not cells[r, c]:
                    top, left = y0 + r * cell * ppm, x0 + c * cell * ppm
                    canvas[round(top) : round(top + cell * ppm),
                           round(left) : round(left + cell * ppm)] = 15  # fmt: skip
    cx, cy = px(*SPOT)
    cv2.circle(canvas, (round(cx), round(cy)), 10, (220, 20, 20), -1)
    scale = 1.2 / ppm
    size = (900, 700)
    rotation = cv2.getRotationMatrix2D((canvas.shape[1] / 2, canvas.shape[0] / 2), turn_deg, scale)
    rotation[:, 2] += np.array(size) / 2 - np.array([canvas.shape[1], canvas.shape[0]]) / 2
    rotation[:, 2] += shift
    return cv2.warpAffine(canvas, rotation, size, flags=cv2.INTER_AREA, borderValue=(40, 40, 40))


def red_centre(image: np.ndarray) -> tuple[float, float]:
    """(row, col) of the red dot's centroid."""
    rgb = image.astype(int)
    rows, cols = np.nonzero((rgb[..., 0] - rgb[..., 1] > 80) & (rgb[..., 0] > 120))
    return float(rows.mean()), float(cols.mean())


def test_a_frame_of_the_rectangle_registers_and_its_pixels_give_the_table_s_millimetres():
    workcell = rectangle_layout(TABLE, 80.0)
    registered = Registration(workcell, 256).register(table_frame(workcell))
    assert sorted(registered.found) == [0, 1, 2, 3]
    assert registered.error_px < 1.0 and registered.offset_px < 20
    # the dot lies where the layout's millimetres say, in the registered view and on the table
    row, col = red_centre(registered.image)
    assert (row, col) == pytest.approx(workcell.mm_to_pixel(*SPOT), abs=1.0)
    assert workcell.pixel_to_mm(row, col) == pytest.approx(SPOT, abs=3.0)  # 2.3 mm a pixel


def test_layout_writes_task_json_s_markers_which_the_import_takes_and_registers_with(tmp_path):
    source = tmp_path / "rec"
    source.mkdir()
    (source / "task.json").write_text(json.dumps(TASK))
    argv = ["workcell", "layout", "--table-mm", "600", "450", "--marker-mm", "80"]
    assert main([*argv, "--task-json", str(source / "task.json")]) == 0
    workcell = rectangle_layout(TABLE, 80.0)
    declared = read_declaration(source, None)  # what lsr data import checks
    assert declared.markers == workcell and declared.name == "towel"
    saved = json.loads((source / "task.json").read_text())
    assert saved["action"] == TASK["action"] and saved["markers"] == workcell.to_json()
    for i, turn in enumerate((2.0, -1.5)):  # one state seen again after the camera moved
        Image.fromarray(table_frame(workcell, turn, (5.0 * i, 0.0))).save(source / f"f{i}.png")
    line = {"image1": "f0.png", "image2": "f1.png", "action": None, "episode": 1}
    (source / "pairs.jsonl").write_text(json.dumps(line) + "\n")
    import_dataset(ImportConfig(source=source, out=tmp_path / "out", test_fraction=0), False)
    data = load_dataset(tmp_path / "out" / "train")
    assert data.manifest["markers"] == workcell.to_json()
    for image in (data.image1[0], data.image2[0]):  # both looks registered to one view
        row, col = red_centre(image)
        expected = workcell.mm_to_pixel(*SPOT, frame=64)
        assert (row, col) == pytest.approx(expected, abs=0.6)


def test_layout_prints_the_section_and_refuses_what_does_not_fit(capsys, tmp_path):
    assert main(["workcell", "layout", "--table-mm", "500", "500", "--marker-mm", "70"]) == 0
    section = json.loads(capsys.readouterr().out)
    assert Workcell.from_json(section) == rectangle_layout((500, 500), 70)
    assert main(["workcell", "layout", "--table-mm", "300", "300", "--marker-mm", "200"]) == 2
    assert "do not fit" in capsys.readouterr().err
    assert main(["workcell", "layout", "--table-mm", "500", "500"]) == 2
    assert "--marker-mm" in capsys.readouterr().err
    bad = tmp_path / "task.json"
    bad.write_text(json.dumps({**TASK, "image_size": 60}))
    argv = ["workcell", "layout", "--table-mm", "500", "500", "--marker-mm", "70"]
    assert main([*argv, "--task-json", str(bad)]) == 2
    assert "image_size" in capsys.readouterr().err
    assert "markers" not in json.loads(bad.read_text())  # nothing written


def test_check_registers_one_frame_and_names_what_it_found(tmp_path, capsys):
    workcell = rectangle_layout(TABLE, 80.0)
    task_json = tmp_path / "task.json"
    task_json.write_text(json.dumps({**TASK, "markers": workcell.to_json()}))
    frame = table_frame(workcell)
    Image.fromarray(frame).save(tmp_path / "frame.png")
    argv = ["workcell", "check", "--task-json", str(task_json), "--image"]
    out = tmp_path / "view.png"
    assert main([*argv, str(tmp_path / "frame.png"), "--out", str(out)]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["markers_found"] == [0, 1, 2, 3] and report["corner_error_px"] < 1
    view = np.asarray(Image.open(out))
    assert view.shape == (256, 256, 3)
    assert red_centre(view) == pytest.approx(workcell.mm_to_pixel(*SPOT), abs=1.0)
    frame[:350, :] = 40  # the far markers covered
    Image.fromarray(frame).save(tmp_path / "covered.png")
    assert main([*argv, str(tmp_path / "covered.png"), "--out", str(out)]) == 2
    assert "table markers were not found: 2 of 4 seen" in capsys.readouterr().err


def test_a_cell_camera_and_relief_round_trip_and_bad_ones_are_named():
    declared = get_task("box_stacking").workcell
    assert declared.camera is not None and declared.relief_mm == 180.0  # a column of three
    assert Workcell.from_json(declared.to_json()) == declared
    plain = rectangle_layout(TABLE, 80.0)
    assert plain.camera is None and "camera" not in plain.to_json()  # bounded as before
    section = {**declared.to_json(), "camera": {"fov_deg": 200, "centre_mm": [0, 0, 500]}}
    with pytest.raises(WorkcellError, match=r"markers\.camera\.fov_deg: .* 1 to 170 degrees"):
        Workcell.from_json(section)
    section["camera"] = {"fov_deg": 60, "centre_mm": [0, 0, -5]}
    with pytest.raises(WorkcellError, match=r"markers\.camera\.centre_mm: .*above the table"):
        Workcell.from_json(section)
    section = {**declared.to_json(), "relief_mm": -1}
    with pytest.raises(WorkcellError, match=r"markers\.relief_mm: expected at least 0"):
        Workcell.from_json(section)
