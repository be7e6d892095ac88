"""`lsr workcell markers` on office paper: the sheet tiled on A4 and Letter pages that print at
100%, every marker whole on one page at its true size and place, and markers taken from a
built-in task, a task.json or a dataset's manifest."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from services.cli import main
from shared import dataset as ds
from shared.marker_sheets import (
    BOTTOM,
    LEFT,
    PAPERS,
    RIGHT,
    TOP,
    SheetError,
    page_svg,
    pages,
    tile,
)
from shared.tasks import get_task
from shared.workcell import Marker, Workcell, marker_cells, rectangle_layout

TASKS = ("box_stacking", "cloth_folding", "rope_box", "tshirt_folding")
LAYOUTS = {
    **{task: get_task(task).workcell for task in TASKS},
    "rectangle": rectangle_layout((600.0, 450.0), 80.0),
    "large_markers": rectangle_layout((900.0, 700.0), 160.0),
}


def svg_size(svg: str) -> tuple[float, float]:
    width, height = re.search(r'<svg[^>]* width="([\d.]+)mm" height="([\d.]+)mm"', svg).groups()
    assert re.search(rf'viewBox="0 0 {width} {height}"', svg)  # one user unit a millimetre
    return float(width), float(height)


def marker_on_page(svg: str, ident: int) -> tuple[np.ndarray, np.ndarray]:
    """The marker's black cells as drawn: their grid (True = white, as `marker_cells`) and
    the (left, top, right, bottom) they span on the page, mm."""
    group = re.search(rf'<g id="marker-{ident}">(.*?)</g>', svg, re.S).group(1)
    rects = np.array(
        re.findall(r'<rect x="([\d.]+)" y="([\d.]+)" width="([\d.]+)" height="([\d.]+)"', group),
        dtype=float,
    )
    left, top = rects[:, 0].min(), rects[:, 1].min()
    right, bottom = (rects[:, 0] + rects[:, 2]).max(), (rects[:, 1] + rects[:, 3]).max()
    n = marker_cells(ident).shape[0]
    cell = (right - left) / n
    white = np.ones((n, n), bool)
    for x, y, w, _ in rects:
        r, c = round((y - top) / cell), round((x - left) / cell)
        white[r, c : c + round(w / cell)] = False
    return white, np.array([left, top, right, bottom])


@pytest.mark.parametrize("paper", ["a4", "letter"])
@pytest.mark.parametrize("name", sorted(LAYOUTS))
def test_every_marker_prints_whole_at_true_size_and_place_on_one_page(name, paper):
    workcell = LAYOUTS[name]
    tiling = tile(workcell, PAPERS[paper])
    made = [page_svg(p) for p in pages(workcell, tiling, f"LSR markers: {name}")]
    size = (PAPERS[paper].width, PAPERS[paper].height)
    found = {}
    for t, svg in zip(tiling.tiles, made, strict=True):
        assert svg_size(svg) == (size[::-1] if tiling.landscape else size)
        width, height = svg_size(svg)
        box = t.box  # the tile fits the page inside its margins
        assert box.right - box.left <= width - LEFT - RIGHT + 1e-6
        assert box.top - box.bottom <= height - TOP - BOTTOM + 1e-6
        assert f"page {t.number} of {len(tiling.tiles)}, row {t.row} of {tiling.rows}" in svg
        for ident in map(int, re.findall(r'<g id="marker-(\d+)">', svg)):
            assert ident not in found, f"marker {ident} on two pages"
            found[ident] = t
            white, (left, top, right, bottom) = marker_on_page(svg, ident)
            marker = next(m for m in workcell.markers if m.id == ident)
            assert np.array_equal(white, marker_cells(ident))  # whole, the right way up
            assert right - left == pytest.approx(marker.side_mm, abs=0.01)  # true size
            assert bottom - top == pytest.approx(marker.side_mm, abs=0.01)
            # inside its tile, not cut
            assert left >= LEFT and right <= LEFT + box.right - box.left
            assert top >= TOP and bottom <= TOP + box.top - box.bottom
            # at its place: the page's tile starts at the tile's table millimetres
            centre_x = box.left + (left + right) / 2 - LEFT
            centre_y = box.top - ((top + bottom) / 2 - TOP)
            assert (centre_x, centre_y) == pytest.approx(marker.centre_mm, abs=0.01)
            assert f"centre x {marker.centre_mm[0]:.1f}, y {marker.centre_mm[1]:.1f} mm" in svg
    assert sorted(found) == sorted(workcell.ids)
    assert {i for t in tiling.tiles for i in t.markers} == set(workcell.ids)
    # the tiles cover the sheet edge to edge: a grid whose neighbours share their edges
    for t in tiling.tiles:
        if t.col < tiling.cols:
            assert tiling.tile_at(t.row, t.col + 1).box.left == t.box.right
        if t.row < tiling.rows:
            assert tiling.tile_at(t.row + 1, t.col).box.top == t.box.bottom


@pytest.mark.parametrize("paper", ["a4", "letter"])
def test_every_page_has_its_scale_bar_crop_marks_and_joins(paper):
    workcell = LAYOUTS["cloth_folding"]
    tiling = tile(workcell, PAPERS[paper])
    assert (tiling.rows, tiling.cols) == (3, 4)  # 705 mm square on 12 pages
    for t, page in zip(tiling.tiles, pages(workcell, tiling, "sheet"), strict=True):
        svg = page_svg(page)
        bar = re.search(r'<path id="scale-bar" d="M ([\d.]+) ([\d.]+) L ([\d.]+) ([\d.]+)"', svg)
        x0, y0, x1, y1 = map(float, bar.groups())
        assert (x1 - x0, y1 - y0) == (100.0, 0.0)
        assert "100 mm" in svg and "actual size" in svg
        assert '<path id="tile"' in svg
        crop = re.findall(r'<path d="M [\d.]+ [\d.]+ L [\d.]+ [\d.]+" stroke="black" '
                          r'stroke-width="0.2"', svg)  # fmt: skip
        assert len(crop) >= 8 + 11  # two lines a corner, and the bar's ticks
        neighbours = sum(
            1 <= r <= tiling.rows and 1 <= c <= tiling.cols
            for r, c in ((t.row - 1, t.col), (t.row + 1, t.col), (t.row, t.col - 1),
                         (t.row, t.col + 1))
        )  # fmt: skip
        assert svg.count("joins here") == neighbours


def test_a_marker_larger_than_the_page_is_refused():
    huge = Workcell(markers=(Marker(0, (0.0, 0.0), 260.0, ((0, 0), (1, 0), (1, 1), (0, 1))),))
    with pytest.raises(SheetError, match="do not fit on A4 pages"):
        tile(huge, PAPERS["a4"])


def test_the_command_writes_pages_as_svgs_or_one_pdf_and_says_how_to_lay_them_out(tmp_path, capsys):
    out = tmp_path / "sheet.svg"
    assert main(["workcell", "markers", "--task", "cloth_folding", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "12 pages, A4 portrait: 3 rows x 4 columns" in printed
    assert "page 1 (row 1, column 1): marker 0" in printed and "100%" in printed
    assert "marker 0 to marker 2: 831.6 mm" in printed  # a diagonal, to check the places
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        f"sheet_p{i}.svg" for i in range(1, 13)
    )
    pdf = tmp_path / "sheet.pdf"
    argv = ["workcell", "markers", "--task", "box_stacking", "--paper", "letter"]
    assert main([*argv, "--out", str(pdf)]) == 0
    data = pdf.read_bytes()
    tiling = tile(get_task("box_stacking").workcell, PAPERS["letter"])
    assert len(re.findall(rb"/Type /Page\b", data)) == len(tiling.tiles)
    boxes = set(re.findall(rb"/MediaBox \[ ?([\d. ]+?) ?\]", data))
    width, height = (PAPERS["letter"].width / 25.4 * 72, PAPERS["letter"].height / 25.4 * 72)
    if tiling.landscape:
        width, height = height, width
    assert len(boxes) == 1
    assert [float(v) for v in boxes.pop().split()] == pytest.approx([0, 0, width, height], abs=0.01)
    # --paper none keeps the one true-size sheet
    single = tmp_path / "whole.svg"
    argv = ["workcell", "markers", "--task", "box_stacking", "--paper", "none"]
    assert main([*argv, "--out", str(single)]) == 0
    assert re.search(r'width="[\d.]+mm" height="[\d.]+mm"', single.read_text())
    assert main([*argv, "--out", str(tmp_path / "whole.pdf")]) == 2


def test_markers_come_from_a_task_json_or_a_dataset_s_manifest(tmp_path, capsys):
    workcell = rectangle_layout((600.0, 450.0), 80.0)
    task_json = tmp_path / "task.json"
    task_json.write_text(json.dumps({"name": "towel", "markers": workcell.to_json()}))
    assert main(["workcell", "markers", "--task-json", str(task_json),
                 "--out", str(tmp_path / "a.svg")]) == 0  # fmt: skip
    first = (tmp_path / "a_p1.svg").read_text()
    assert "LSR markers: towel (DICT_4X4_50)" in first and '<g id="marker-0">' in first
    data = tmp_path / "data" / "train"
    data.mkdir(parents=True)
    manifest = {"format": ds.FORMAT, "version": ds.VERSION, "task": "towel", "shards": [],
                "markers": workcell.to_json()}  # fmt: skip
    (data / "manifest.json").write_text(json.dumps(manifest))
    for folder in (data, data.parent):  # a dataset, or an import's folder (its task.json)
        if folder == data.parent:
            (folder / "task.json").write_text(task_json.read_text())
        out = tmp_path / f"{folder.name}.svg"
        assert main(["workcell", "markers", "--data", str(folder), "--out", str(out)]) == 0
        assert (tmp_path / f"{folder.name}_p1.svg").read_text() == first
    capsys.readouterr()
    task_json.write_text(json.dumps({"name": "fixed", "markers": None}))
    assert main(["workcell", "markers", "--task-json", str(task_json),
                 "--out", str(tmp_path / "b.svg")]) == 2  # fmt: skip
    assert "has no markers" in capsys.readouterr().err
    task_json.write_text(json.dumps({"name": "towel"}))
    assert main(["workcell", "markers", "--task-json", str(task_json),
                 "--out", str(tmp_path / "b.svg")]) == 2  # fmt: skip
    assert 'no "markers" section' in capsys.readouterr().err
