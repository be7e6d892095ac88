"""The workcell: fiducial markers at fixed places on the table, and where the canonical view
sees them.

A camera that moves (a bumped tripod, a second cell) sees the table from another pose; the
markers tell where the table is in every frame, so that `shared.registration` can bring the
frame back to the one canonical view the models were trained on, as calibrated folding cells
do. A `Workcell` is pure data (no MuJoCo, no OpenCV at import): tasks report it, datasets and
imported `task.json` carry it, `lsr workcell markers` prints it at true size (tiled on office
paper by `shared.marker_sheets`), and its markers' places in millimetres relate the canonical
view's pixels to the table (`Workcell.pixel_to_mm`), which is what a robot acts in.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

DICTIONARY = "DICT_4X4_50"  # 4 x 4 bits: the largest cells for a given marker size
BORDER_CELLS = 1  # a marker is (bits + 2) cells a side: one black cell of border all round
CELLS = 4 + 2 * BORDER_CELLS  # cells across a printed marker of DICTIONARY


LAYOUTS = Path(__file__).parent / "tasks" / "workcells"  # one JSON per built-in task

# The frame's field of view over the canonical one (tangent of the half-angle): 111 degrees, so
# that the markers and the view stay in it with the camera turned 20 degrees about every axis
# (benchmarks/frame_field.py; at 2.2 a third of such frames lost their far markers).
FRAME_SCALE = 4.0
FRAME_SIZE = 720  # pixels: 0.70 frame pixels per canonical pixel at 256, as 400 at 2.2 gave


class WorkcellError(ValueError):
    """A workcell description that cannot be used; the message names the field."""


@dataclass(frozen=True)
class Marker:
    """One square marker: its id, where it lies on the table and where the canonical view
    sees its corners."""

    id: int
    centre_mm: tuple[float, float]  # on the table: x right, y away from the camera
    side_mm: float  # the whole marker, border included
    # (4, 2) (x, y) pixels of the canonical frame, in OpenCV's order: the printed marker's
    # top-left, top-right, bottom-right, bottom-left (top = towards +y on the table).
    corners: tuple[tuple[float, float], ...]

    def to_json(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "centre_mm": [round(v, 3) for v in self.centre_mm],
            "side_mm": round(self.side_mm, 3),
            "corners": [[round(x, 3), round(y, 3)] for x, y in self.corners],
        }


@dataclass(frozen=True)
class CellCamera:
    """The cell camera as registration needs it to tell what a moved camera does to what stands
    above the table: the vertical field of view of its whole frames (square pixels, the
    principal point at the frame's centre) and its centre at the nominal pose, table millimetres
    (x, y as the markers', z above the table)."""

    fov_deg: float
    centre_mm: tuple[float, float, float]

    def to_json(self) -> dict[str, Any]:
        return {
            "fov_deg": round(self.fov_deg, 4),
            "centre_mm": [round(v, 2) for v in self.centre_mm],
        }


@dataclass(frozen=True)
class Workcell:
    """The markers of one task's table and the levels their cells take in the canonical view.

    `corners` may lie outside the frame: the markers sit round the view the models see, on
    the table the camera sees beyond it, so that nothing on the table ever covers them.
    """

    markers: tuple[Marker, ...]
    # markers a frame must show to be registered: fewer extrapolate the view too far where
    # the markers lie to one side of it (the box camera's lie low)
    min_markers: int = 3
    frame: int = 256  # the canonical frame's side in pixels (the actions' frame)
    dictionary: str = DICTIONARY
    # Per channel, 0..255: what the markers' black and white cells look like in the canonical
    # view; registration maps each frame's measured levels onto these.
    black: tuple[float, float, float] = (0.0, 0.0, 0.0)
    white: tuple[float, float, float] = (255.0, 255.0, 255.0)
    # With the camera known, registration bounds a moved camera by the parallax of what stands
    # up to `relief_mm` above the table (0: a flat scene, any pose whose markers are seen);
    # without it, by how far the view moved (`shared.registration.Bounds.max_offset_px`).
    camera: CellCamera | None = None
    relief_mm: float = 0.0

    @property
    def ids(self) -> list[int]:
        return [m.id for m in self.markers]

    def corners(self) -> np.ndarray:
        """(N, 4, 2) float64 canonical-frame corners, in the order of `markers`."""
        return np.array([m.corners for m in self.markers], dtype=np.float64)

    def to_json(self) -> dict[str, Any]:
        return {
            "dictionary": self.dictionary,
            "frame": self.frame,
            "ids": self.ids,
            "min_markers": self.min_markers,
            "markers": [m.to_json() for m in self.markers],
            "black": [round(v, 2) for v in self.black],
            "white": [round(v, 2) for v in self.white],
            **(
                {}
                if self.camera is None
                else {"camera": self.camera.to_json(), "relief_mm": round(self.relief_mm, 2)}
            ),
        }

    @classmethod
    def from_json(cls, obj: Any, where: str = "markers") -> Workcell | None:
        """A workcell from its JSON; None for `null` (a camera that never moves)."""
        if obj is None:
            return None
        if not isinstance(obj, dict):
            raise WorkcellError(f"{where}: expected an object or null")
        dictionary = obj.get("dictionary", DICTIONARY)
        if dictionary != DICTIONARY:
            raise WorkcellError(f"{where}.dictionary: only {DICTIONARY} is supported")
        frame = _number(obj.get("frame", 256), f"{where}.frame")
        items = obj.get("markers")
        if not isinstance(items, list) or not items:
            raise WorkcellError(f"{where}.markers: expected a non-empty list of markers")
        markers = []
        for i, item in enumerate(items):
            at = f"{where}.markers[{i}]"
            if not isinstance(item, dict):
                raise WorkcellError(f"{at}: expected an object")
            ident = item.get("id")
            if isinstance(ident, bool) or not isinstance(ident, int) or not 0 <= ident < 50:
                raise WorkcellError(f"{at}.id: expected an integer 0..49 ({DICTIONARY})")
            corners = np.asarray(item.get("corners"), dtype=object)
            if corners.shape != (4, 2):
                raise WorkcellError(f"{at}.corners: expected four [x, y] pairs")
            markers.append(
                Marker(
                    id=ident,
                    centre_mm=_pair(item.get("centre_mm", [0.0, 0.0]), f"{at}.centre_mm"),
                    side_mm=_number(item.get("side_mm", 0.0), f"{at}.side_mm"),
                    corners=tuple(_pair(c, f"{at}.corners") for c in corners.tolist()),
                )
            )
        if len({m.id for m in markers}) != len(markers):
            raise WorkcellError(f"{where}.markers: every id may appear once")
        least = obj.get("min_markers", min(3, len(markers)))
        if isinstance(least, bool) or not isinstance(least, int) or not 1 <= least <= len(markers):
            raise WorkcellError(f"{where}.min_markers: an integer from 1 to {len(markers)}")
        return cls(
            markers=tuple(markers),
            min_markers=least,
            frame=int(frame),
            black=_triple(obj.get("black", [0, 0, 0]), f"{where}.black"),
            white=_triple(obj.get("white", [255, 255, 255]), f"{where}.white"),
            camera=_camera(obj.get("camera"), f"{where}.camera"),
            relief_mm=_number(obj.get("relief_mm", 0.0), f"{where}.relief_mm", low=0.0),
        )

    def table_corners_mm(self) -> np.ndarray:
        """(N, 4, 2) the markers' printed corners on the table (mm), in the order of
        `corners()`: top-left, top-right, bottom-right, bottom-left, top towards +y."""
        out = []
        for m in self.markers:
            (x, y), h = m.centre_mm, m.side_mm / 2
            out.append([(x - h, y + h), (x + h, y + h), (x + h, y - h), (x - h, y - h)])
        return np.array(out, dtype=np.float64)

    def table_homography(self) -> np.ndarray:
        """(3, 3) table millimetres (x, y) -> canonical pixels (x = column, y = row, pixel
        centres at integers), fitted to every marker's corners: the markers lie on the table's
        plane, and the canonical view is an image of that plane, so one homography relates
        them. Exact for points on the table; a point above it (the top of a stack) maps to
        where its line of sight meets the table, off by its height's parallax."""
        if any(m.side_mm <= 0 for m in self.markers):
            raise WorkcellError(
                "markers: every marker needs centre_mm and side_mm (its place on the table) "
                "to relate pixels to millimetres"
            )
        return _homography(self.table_corners_mm().reshape(-1, 2), self.corners().reshape(-1, 2))

    def pixel_to_mm(self, row: float, col: float, frame: int | None = None) -> tuple[float, float]:
        """The table point (x, y) in mm that the centre of pixel (row, col) of the registered
        view shows, the pixel counted in a `frame` x `frame` image (an action's frame, say
        task.json's `frame`; default this workcell's). What a robot needs to act on a plan:
        the markers fix the table's plane, so only its table-to-base transform remains."""
        scale = self.frame / (frame or self.frame)
        u, v = (col + 0.5) * scale - 0.5, (row + 0.5) * scale - 0.5
        x, y = _apply(np.linalg.inv(self.table_homography()), np.array([[u, v]]))[0]
        return float(x), float(y)

    def mm_to_pixel(self, x: float, y: float, frame: int | None = None) -> tuple[float, float]:
        """The (row, col) of a `frame` x `frame` view (default this workcell's) at which the
        table point (x, y) mm lies, as continuous pixel indices (round them for an action):
        how a robot's recorded grasp becomes a pixel action."""
        u, v = _apply(self.table_homography(), np.array([[x, y]], dtype=np.float64))[0]
        scale = (frame or self.frame) / self.frame
        return float((v + 0.5) * scale - 0.5), float((u + 0.5) * scale - 0.5)


def rectangle_layout(
    table_mm: tuple[float, float],
    marker_mm: float,
    inset_mm: float | None = None,
    frame: int = 256,
    dictionary: str = DICTIONARY,
) -> Workcell:
    """Markers for a cell without a simulator: a W x H rectangle of table (mm), one marker of
    side `marker_mm` inside each corner (ids 0 far left, 1 far right, 2 near right, 3 near
    left, as the built-in cells number theirs), its outer edges `inset_mm` from the
    rectangle's edges (default one of its cells, a sixth of its side: the white margin the
    detector wants round its black border). The table frame's origin is the rectangle's
    centre, x to the right as the camera sees it, y away from the camera; the canonical view
    looks straight down on the rectangle, its centre at the view's centre and
    `frame / max(W, H)` pixels a millimetre (the same on both axes: a non-square rectangle
    leaves bands of what lies beyond it)."""
    width, height = (float(v) for v in table_mm)
    side = float(marker_mm)
    inset = side / CELLS if inset_mm is None else float(inset_mm)
    if dictionary != DICTIONARY:
        raise WorkcellError(f"dictionary: only {DICTIONARY} is supported")
    if not (width > 0 and height > 0 and side > 0 and inset >= 0 and frame > 0):
        raise WorkcellError("table and marker sizes must be positive, the inset not negative")
    if 2 * (side + inset) >= min(width, height):
        raise WorkcellError(
            f"markers of {side:g} mm, {inset:g} mm from the edges, do not fit twice across "
            f"the {min(width, height):g} mm side of the table: smaller markers or a larger table"
        )
    ppm = frame / max(width, height)  # pixels a millimetre
    centre = (frame - 1) / 2  # pixel centres at integers: the view spans -0.5 .. frame - 0.5
    off_x, off_y = width / 2 - inset - side / 2, height / 2 - inset - side / 2
    places = [(-off_x, off_y), (off_x, off_y), (off_x, -off_y), (-off_x, -off_y)]
    markers = []
    for ident, (cx, cy) in enumerate(places):
        h = side / 2
        square = [(cx - h, cy + h), (cx + h, cy + h), (cx + h, cy - h), (cx - h, cy - h)]
        corners = tuple((round(centre + ppm * x, 3), round(centre - ppm * y, 3)) for x, y in square)
        markers.append(Marker(ident, (round(cx, 3), round(cy, 3)), round(side, 3), corners))
    return Workcell(markers=tuple(markers), min_markers=3, frame=frame, dictionary=dictionary)


def _homography(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The least-squares homography (normalised DLT) taking (N, 2) `source` to `target`."""

    def normaliser(points: np.ndarray) -> np.ndarray:
        mean = points.mean(axis=0)
        spread = np.sqrt(((points - mean) ** 2).sum(axis=1).mean() / 2) or 1.0
        return np.array([[1 / spread, 0, -mean[0] / spread], [0, 1 / spread, -mean[1] / spread],
                         [0, 0, 1]])  # fmt: skip

    a, b = normaliser(source), normaliser(target)
    src, dst = _apply(a, source), _apply(b, target)
    rows = []
    for (x, y), (u, v) in zip(src, dst, strict=True):
        rows.append([-x, -y, -1, 0, 0, 0, u * x, u * y, u])
        rows.append([0, 0, 0, -x, -y, -1, v * x, v * y, v])
    _, _, vt = np.linalg.svd(np.array(rows))
    normalised = vt[-1].reshape(3, 3)
    homography = np.linalg.inv(b) @ normalised @ a
    return homography / homography[2, 2]


def _apply(homography: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 2) points through a homography."""
    lifted = np.column_stack([points, np.ones(len(points))]) @ homography.T
    return lifted[:, :2] / lifted[:, 2:3]


def _number(value: Any, where: str, low: float | None = None) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise WorkcellError(f"{where}: expected a finite number")
    if low is not None and value < low:
        raise WorkcellError(f"{where}: expected at least {low:g}, got {value:g}")
    return float(value)


def _camera(value: Any, where: str) -> CellCamera | None:
    if value is None:
        return None
    if not isinstance(value, dict):
        raise WorkcellError(f"{where}: expected an object with fov_deg and centre_mm, or null")
    fov = _number(value.get("fov_deg"), f"{where}.fov_deg")
    if not 1.0 <= fov <= 170.0:
        raise WorkcellError(f"{where}.fov_deg: a field of view from 1 to 170 degrees")
    centre = value.get("centre_mm")
    if not isinstance(centre, list | tuple) or len(centre) != 3:
        raise WorkcellError(f"{where}.centre_mm: expected [x, y, z]")
    x, y, z = (_number(v, f"{where}.centre_mm") for v in centre)
    if z <= 0:
        raise WorkcellError(f"{where}.centre_mm: the camera stands above the table (z > 0)")
    return CellCamera(fov_deg=fov, centre_mm=(x, y, z))


def _pair(value: Any, where: str) -> tuple[float, float]:
    if not isinstance(value, list | tuple) or len(value) != 2:
        raise WorkcellError(f"{where}: expected [x, y]")
    return _number(value[0], where), _number(value[1], where)


def _triple(value: Any, where: str) -> tuple[float, float, float]:
    if not isinstance(value, list | tuple) or len(value) != 3:
        raise WorkcellError(f"{where}: expected [r, g, b]")
    r, g, b = (_number(v, where) for v in value)
    return r, g, b


def load_workcell(task: str) -> Workcell | None:
    """A built-in task's workcell, as `lsr workcell layout` wrote it; None when it has none."""
    path = LAYOUTS / f"{task}.json"
    if not path.is_file():
        return None
    return Workcell.from_json(json.loads(path.read_text()), where=f"{path.name}")


@cache
def marker_cells(marker_id: int) -> np.ndarray:
    """(6, 6) bool, True where the printed marker is white, row 0 at its top."""
    import cv2  # only what draws or detects markers needs OpenCV

    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, DICTIONARY))
    side = dictionary.markerSize + 2 * BORDER_CELLS
    cells = cv2.aruco.generateImageMarker(dictionary, marker_id, side) > 127
    cells.setflags(write=False)
    return cells


def markers_svg(workcell: Workcell, task: str) -> str:
    """A printable sheet of the table at true size (millimetres): every marker at its place,
    the quiet white margin it needs, and a cross at the table frame's origin."""
    cells = {m.id: marker_cells(m.id) for m in workcell.markers}
    margin = 20.0
    xs = [m.centre_mm[0] for m in workcell.markers]
    ys = [m.centre_mm[1] for m in workcell.markers]
    half = max(m.side_mm for m in workcell.markers) / 2 + margin
    left, right = min(xs) - half, max(xs) + half
    bottom, top = min(ys) - half, max(ys) + half
    width, height = right - left, top - bottom

    def at(x: float, y: float) -> tuple[float, float]:  # table mm -> sheet mm (y down)
        return x - left, top - y

    parts = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width:.1f}mm" height="{height:.1f}mm" '
        f'viewBox="0 0 {width:.3f} {height:.3f}">',
        f"<title>LSR workcell markers: {task} ({workcell.dictionary})</title>",
        f'<rect x="0" y="0" width="{width:.3f}" height="{height:.3f}" fill="white"/>',
    ]
    for marker in workcell.markers:
        grid = cells[marker.id]
        n = grid.shape[0]
        cell = marker.side_mm / n
        half_side = marker.side_mm / 2
        x0, y0 = at(marker.centre_mm[0] - half_side, marker.centre_mm[1] + half_side)
        parts.append(f'<g id="marker-{marker.id}">')
        for r in range(n):
            for c in range(n):
                if not grid[r, c]:
                    parts.append(
                        f'<rect x="{x0 + c * cell:.3f}" y="{y0 + r * cell:.3f}" '
                        f'width="{cell:.3f}" height="{cell:.3f}" fill="black"/>'
                    )
        label_x, label_y = x0, y0 + marker.side_mm + 4
        parts.append(
            f'<text x="{label_x:.2f}" y="{label_y:.2f}" font-size="3" font-family="sans-serif">'
            f"id {marker.id}: centre ({marker.centre_mm[0]:.1f}, {marker.centre_mm[1]:.1f}) mm, "
            f"side {marker.side_mm:.1f} mm</text></g>"
        )
    ox, oy = at(0.0, 0.0)
    parts.append(
        f'<path d="M {ox - 5:.2f} {oy:.2f} H {ox + 5:.2f} M {ox:.2f} {oy - 5:.2f} V {oy + 5:.2f}" '
        'stroke="black" stroke-width="0.3" fill="none"/>'
    )
    parts.append(
        f'<text x="{ox + 2:.2f}" y="{oy - 2:.2f}" font-size="3" font-family="sans-serif">'
        "table origin (x right, y away from the camera)</text>"
    )
    parts.append("</svg>")
    return "\n".join(parts) + "\n"
