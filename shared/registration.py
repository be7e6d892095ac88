"""Registration: a camera frame brought to the task's canonical table view, before any model.

One step every image passes on its way in (data generation, serving, the closed loop), as
calibrated folding cells re-project every capture to one table view: find the workcell's
markers on the full-resolution frame (OpenCV's ArUco, sub-pixel corners), fit the homography
from the frame to the canonical frame (RANSAC), check that it is plausible, warp, map the
markers' measured black and white onto the workcell's levels (per channel, a gain and an
offset), and resize to the model's size. What cannot be registered raises RegistrationError
with a reason that says which markers were missing or what was implausible.
"""

from __future__ import annotations

import functools
import math
import threading
from dataclasses import dataclass, field

import cv2
import numpy as np

from shared.workcell import CellCamera, Workcell, marker_cells

NOT_FOUND = "the table markers were not found"
_THRESHOLD_WINDOW = 23  # the detector's widest adaptive threshold window (OpenCV's default)
# A marker whose corners moved less than this (frame px) since the last frame is taken as found
# there, without the detector: the detector's own corners lie about as close to the true ones.
TRACK_PX = 0.5
HALF_CELL_MARGIN = 0.1  # px: a marker's half cell this near x.5 may refine with either window
# Corners all this near (canonical px) a least-squares fit: RANSAC (3 px) would keep them all,
# and one corner 2-3 px off, pulling the fit by a sixteenth of that, lies farther.
LEAST_SQUARES_PX = 1.5


class RegistrationError(ValueError):
    """A frame that cannot be brought to the table frame; the message says why, and starts
    with NOT_FOUND whatever the markers lacked (too few seen, an implausible homography, too
    faint to read the light): the refusal contract names the markers so."""


@dataclass(frozen=True)
class Bounds:
    """What a plausible homography looks like: the defaults lie above what `shifted` frames,
    which double every camera range, gave (250 random states a task: corner RMS at most 1.83
    px for box stacking, 0.85 for cloth; the view moved at most 39.5 px; `camera`: 1.54 and
    19.5; a box column's top 3.16 px of parallax at 64 px, `camera` 1.44, rope-box's boxes
    0.35), far below what a marker moved on the table or a frame turned round gives."""

    max_error_px: float = 2.5  # RMS reprojection error of the corners, canonical pixels
    max_offset_px: float = 60.0  # how far the view's corners may lie from where they should
    # where the workcell knows its camera (`Workcell.camera`) instead of max_offset_px: how far
    # a point `relief_mm` above the table may lie from where the nominal camera shows it, in
    # pixels of the model's view (at 64 px: 1 px is 4 of the canonical frame's)
    max_parallax_px: float = 4.0
    min_contrast: float = 40.0  # white minus black of the markers' cells, levels of 255


@dataclass(frozen=True)
class Registered:
    """A registered image and how it was registered."""

    image: np.ndarray  # uint8 (size, size, 3): the canonical view at the model's size
    homography: np.ndarray  # (3, 3) frame pixels -> canonical pixels
    error_px: float  # RMS reprojection error of the markers' corners, canonical pixels
    offset_px: float  # the farthest the view's corners lie from the nominal pose's
    found: tuple[int, ...]  # the ids of the markers used
    gain: np.ndarray = field(default_factory=lambda: np.ones(3))
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))
    parallax_px: float = 0.0  # where the camera is known: see Parallax (model pixels)


class Parallax:
    """How far a point `relief_mm` above the table lies, in the registered view, from where the
    nominal camera shows it: registration maps the table's plane exactly from any pose, and
    what stands above it is seen along another line of sight, which meets the table elsewhere.
    It depends only on where the camera's centre moved (a camera turned about its centre gives
    none), found from the frame's homography and the camera's field of view."""

    def __init__(self, workcell: Workcell, camera: CellCamera) -> None:
        self.relief = workcell.relief_mm
        self.fov = math.radians(camera.fov_deg)
        self.nominal = np.asarray(camera.centre_mm, np.float64)
        self.to_canonical = workcell.table_homography()  # table mm -> canonical pixels
        n = workcell.frame
        view = np.stack(np.meshgrid(np.linspace(0, n - 1, 9), np.linspace(0, n - 1, 9)), -1)
        self.points = _apply(np.linalg.inv(self.to_canonical), view.reshape(-1, 2))  # table mm
        # where the nominal camera shows those points `relief` above the table: fixed
        self.seen_nominally = _apply(
            self.to_canonical, _on_table(self.nominal, self.points, self.relief)
        )

    def __call__(self, homography: np.ndarray, width: int, height: int) -> tuple[float, float]:
        """(how far the camera's centre moved, mm; the largest parallax, canonical pixels) for
        a frame of `width` x `height` registered by `homography` (frame -> canonical)."""
        table_to_frame = np.linalg.inv(homography) @ self.to_canonical
        centre = camera_centre(table_to_frame, self.fov, width, height)
        moved = float(np.linalg.norm(centre - self.nominal))
        if self.relief <= 0:
            return moved, 0.0
        seen = _apply(self.to_canonical, _on_table(centre, self.points, self.relief))
        return moved, float(np.linalg.norm(seen - self.seen_nominally, axis=1).max())


def camera_centre(table_to_frame: np.ndarray, fov: float, width: int, height: int) -> np.ndarray:
    """The centre (table mm, z above the table) of a pinhole camera of vertical field of view
    `fov` (radians; square pixels, the principal point at the frame's centre) whose frame sees
    the table through `table_to_frame` (table mm -> frame pixels)."""
    focal = height / 2 / math.tan(fov / 2)
    intrinsics = np.array([[focal, 0, (width - 1) / 2], [0, focal, (height - 1) / 2], [0, 0, 1]])
    columns = np.linalg.solve(intrinsics, table_to_frame)  # [r1 r2 t], up to one scale
    scale = 2 / (np.linalg.norm(columns[:, 0]) + np.linalg.norm(columns[:, 1]))
    if columns[2, 2] < 0:  # the table lies in front of the camera
        scale = -scale
    r1, r2, t = (scale * columns[:, i] for i in range(3))
    u, _, vt = np.linalg.svd(np.column_stack([r1, r2, np.cross(r1, r2)]))
    return -(u @ vt).T @ t


def _on_table(centre: np.ndarray, points: np.ndarray, height: float) -> np.ndarray:
    """Where the lines of sight from `centre` through the points `height` above the table
    points (N, 2) meet the table."""
    return centre[:2] + (points - centre[:2]) * (centre[2] / (centre[2] - height))


class Registration:
    """Frames of one workcell -> canonical views at `size` pixels.

    `photometric` False skips the colour step (for measuring what it does). `workcell` None
    is a camera that never moves: frames must already be the canonical view, and are only
    resized.
    """

    def __init__(
        self,
        workcell: Workcell | None,
        size: int,
        photometric: bool = True,
        bounds: Bounds | None = None,
    ) -> None:
        self.workcell = workcell
        self.size = size
        self.photometric = photometric
        self.bounds = bounds or Bounds()
        self._local = threading.local()  # OpenCV detectors are not shared between threads
        self._last: dict[tuple[int, ...], dict[int, np.ndarray]] = {}  # frame shape -> markers
        if workcell is not None:
            self._corners = {m.id: np.asarray(m.corners, np.float64) for m in workcell.markers}
            self._cells = {m.id: _cell_centres(m.id, self._corners[m.id]) for m in workcell.markers}
            self._bits = {m.id: marker_cells(m.id) for m in workcell.markers}
            self._sides = {ident: bits.shape[0] for ident, bits in self._bits.items()}  # cells
            self._black = np.asarray(workcell.black, np.float64)
            self._white = np.asarray(workcell.white, np.float64)
            if workcell.camera is not None:
                self._parallax = Parallax(workcell, workcell.camera)

    def _detector(self) -> cv2.aruco.ArucoDetector:
        detector = getattr(self._local, "detector", None)
        if detector is None:
            assert self.workcell is not None
            dictionary = cv2.aruco.getPredefinedDictionary(
                getattr(cv2.aruco, self.workcell.dictionary)
            )
            parameters = cv2.aruco.DetectorParameters()
            parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
            # measured on `camera` and `shifted` frames (benchmarks/bench_registration.py):
            # markers near the frame's edge and foreshortened ones are found more often
            parameters.minDistanceToBorder = 1
            parameters.adaptiveThreshWinSizeStep = 4
            parameters.adaptiveThreshWinSizeMax = _THRESHOLD_WINDOW
            parameters.polygonalApproxAccuracyRate = 0.05
            parameters.perspectiveRemovePixelPerCell = 8
            detector = cv2.aruco.ArucoDetector(dictionary, parameters)
            self._local.detector = detector
        return detector

    def detect(self, frame: np.ndarray) -> dict[int, np.ndarray]:
        """The workcell's markers found in `frame`: id -> (4, 2) frame corners.

        A fixed camera's markers have not moved since its last frame of this size: those are
        refined from where they were and read back, with no detector (`_tracked`). The others
        are looked for round where the last frame showed them (about a third of the pixels),
        then in the whole frame, then at twice the scale: small, blurred markers far from the
        camera decode there (every box-stacking state at `camera` registers with it; 5 of 288
        did not without). Every corner is then refined on the whole frame (`_refine`), so that
        where a marker was found does not move its corners."""
        gray = cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_RGB2GRAY)
        last = self._last.get(gray.shape, {})
        tracked = self._tracked(gray, last)
        found = self._near(gray, {i: q for i, q in last.items() if i not in tracked})
        if len(tracked) + len(found) < len(self._corners):
            for ident, quad in self._markers(gray, 1.0).items():
                if ident not in tracked:
                    found.setdefault(ident, quad)
        if len(tracked) + len(found) < len(self._corners):
            doubled = cv2.resize(gray, None, fx=2, fy=2, interpolation=cv2.INTER_LINEAR)
            for ident, quad in self._markers(doubled, 2.0).items():
                if ident not in tracked:
                    found.setdefault(ident, quad)
        found = {ident: _refine(gray, quad, self._sides[ident]) for ident, quad in found.items()}
        found.update(tracked)
        if found:  # a plain dict swap: threads sharing this registration never see half of it
            self._last = {**self._last, gray.shape: found}
        return found

    def _tracked(self, gray: np.ndarray, last: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """The markers of `last` that have not moved (a fixed camera's next frame): each corner
        refined from where it was, kept where it moved under TRACK_PX (then its start and the
        detector's both lie within the refinement's reach of one corner, which both reach) and
        the marker's cells still read as its own."""
        refined = {ident: _refine(gray, quad, self._sides[ident]) for ident, quad in last.items()}
        still = [i for i, quad in refined.items() if np.abs(quad - last[i]).max() < TRACK_PX]
        if not still:
            return {}
        quads = np.stack([refined[i] for i in still])
        reads = _reads(gray, quads, np.stack([self._bits[i] for i in still]), self.bounds)
        return {ident: refined[ident] for ident, ok in zip(still, reads, strict=True) if ok}

    def _near(self, gray: np.ndarray, last: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
        """Each marker of `last` looked for in a window round where it was: the marker and a
        margin as wide as the marker (and wider than the widest threshold window, so that the
        marker's pixels threshold as in the whole frame)."""
        found: dict[int, np.ndarray] = {}
        height, width = gray.shape
        for ident, quad in last.items():
            (x0, y0), (x1, y1) = quad.min(axis=0), quad.max(axis=0)
            margin = max(x1 - x0, y1 - y0, _THRESHOLD_WINDOW)
            left, top = max(0, int(x0 - margin)), max(0, int(y0 - margin))
            right, bottom = min(width, int(x1 + margin) + 1), min(height, int(y1 + margin) + 1)
            if right - left < 8 or bottom - top < 8:
                continue
            window = np.ascontiguousarray(gray[top:bottom, left:right])
            # only outlines of about the marker's length: the window's clutter is not decoded
            perimeter = float(cv2.arcLength(quad.astype(np.float32), True)) / max(window.shape)
            seen = self._markers(window, 1.0, (0.5 * perimeter, 2.0 * perimeter)).get(ident)
            if seen is not None:
                found[ident] = seen + np.array([left, top], np.float64)
        return found

    def _markers(
        self, gray: np.ndarray, scale: float, perimeter: tuple[float, float] | None = None
    ) -> dict[int, np.ndarray]:
        """Markers in `gray` (`scale` times the frame); `perimeter`: the outlines' lengths
        looked at, as shares of the image's longer side (the detector's default otherwise)."""
        detector = self._detector()
        if perimeter is not None:
            parameters = detector.getDetectorParameters()
            parameters.minMarkerPerimeterRate, parameters.maxMarkerPerimeterRate = perimeter
            detector = cv2.aruco.ArucoDetector(detector.getDictionary(), parameters)
        corners, ids, _ = detector.detectMarkers(gray)
        found: dict[int, np.ndarray] = {}
        if ids is None:
            return found
        for ident, quad in zip(ids.reshape(-1).tolist(), corners, strict=True):
            if ident in self._corners and ident not in found:
                # pixel centres at integers at both scales
                found[ident] = (quad.reshape(4, 2).astype(np.float64) + 0.5) / scale - 0.5
        return found

    def _found(self, frame: np.ndarray) -> dict[int, np.ndarray]:
        """`detect`, refusing a frame that shows too few of the markers."""
        assert self.workcell is not None
        wc, found = self.workcell, self.detect(frame)
        if len(found) < wc.min_markers:
            missing = [i for i in wc.ids if i not in found]
            raise RegistrationError(
                f"{NOT_FOUND}: {len(found)} of {len(wc.ids)} seen "
                f"(missing ids {missing}; {wc.dictionary}), at least {wc.min_markers} needed"
            )
        return found

    def _fit(self, found: dict[int, np.ndarray]) -> tuple[np.ndarray, float]:
        """The homography from the found corners to the canonical ones (least squares, or
        RANSAC where a corner disagrees), and the RMS reprojection error of the corners
        through it."""
        ids = sorted(found)
        source = np.concatenate([found[i] for i in ids])
        target = np.concatenate([self._corners[i] for i in ids])
        # Least squares over every corner costs half of RANSAC, and is kept where every corner
        # lies within LEAST_SQUARES_PX of it: RANSAC keeping them all ends in the same fit, and
        # leaving one out it lay up to 0.45 frame px away, farther from the truth more often
        # than not (docs/camera.md, Cost). A corner 2-3 px off drew least squares 4.4 px from
        # the truth on a box frame: RANSAC leaves such a corner out.
        homography, _ = cv2.findHomography(source, target, 0)
        residuals = None if homography is None else _apply(homography, source) - target
        if residuals is None or np.linalg.norm(residuals, axis=1).max() > LEAST_SQUARES_PX:
            homography, _ = cv2.findHomography(source, target, cv2.RANSAC, 3.0)
            if homography is None:
                raise RegistrationError(
                    f"{NOT_FOUND}: they give no homography (degenerate corners)"
                )
            residuals = _apply(homography, source) - target
        return homography, _rms(residuals)

    def register(self, frame: np.ndarray) -> Registered:
        """`frame` (uint8 (H, W, 3), any size) as the canonical view at the model's size."""
        frame = np.asarray(frame)
        if frame.ndim != 3 or frame.shape[2] != 3 or frame.dtype != np.uint8:
            raise RegistrationError(f"expected a uint8 RGB image, got {frame.dtype} {frame.shape}")
        if self.workcell is None:
            return Registered(_resize(frame, self.size), np.eye(3), 0.0, 0.0, ())
        b, wc = self.bounds, self.workcell
        found = self._found(frame)
        ids = sorted(found)
        homography, error = self._fit(found)
        offset = self._offset(homography, frame.shape[1], frame.shape[0])
        geometric = wc.camera is not None  # parallax bounds the pose, not how far it moved
        if not error <= b.max_error_px or not (geometric or offset <= b.max_offset_px):
            view = "" if geometric else f", view moved {offset:.1f} px (bound {b.max_offset_px})"
            raise RegistrationError(
                f"{NOT_FOUND}: ids {ids} give an implausible homography: corner error "
                f"{error:.2f} px (bound {b.max_error_px}){view}"
            )
        parallax = 0.0
        if geometric:
            moved, parallax = self._parallax(homography, frame.shape[1], frame.shape[0])
            parallax *= self.size / wc.frame  # pixels of the model's view
            if not parallax <= b.max_parallax_px:
                raise RegistrationError(
                    f"the camera stands {moved:.0f} mm from its place: what stands "
                    f"{wc.relief_mm:g} mm above the table would lie {parallax:.2f} px from "
                    f"where the model saw it (bound {b.max_parallax_px} px at {self.size} px)"
                )
        canonical = cv2.warpPerspective(
            frame,
            homography,
            (wc.frame, wc.frame),
            flags=cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
        view = _resize(canonical, self.size)
        gain, shift = np.ones(3), np.zeros(3)
        if self.photometric:  # on the model's pixels, not the canonical frame's 16 times more
            gain, shift = self._levels(frame, homography, ids)
            view = _map_levels(view, gain, shift)
        return Registered(
            view,
            homography,
            error,
            offset,
            tuple(ids),
            gain,
            shift,
            parallax,
        )

    def _offset(self, homography: np.ndarray, width: int, height: int) -> float:
        """How far (canonical pixels) the frame's view of the canonical square lies from a
        camera at the nominal pose, which sees the canonical view centred and at scale."""
        assert self.workcell is not None
        n = self.workcell.frame
        square = np.array([[0, 0], [n, 0], [n, n], [0, n]], np.float64) - 0.5
        seen = _apply(np.linalg.inv(homography), square)  # where the frame shows them
        # the nominal pose: the frame's centre is the canonical centre, at the frame's scale
        centre = np.array([(width - 1) / 2, (height - 1) / 2])
        scale = _scale(homography, centre)
        nominal = centre + (square - (n - 1) / 2) / scale
        return float(np.max(np.linalg.norm(seen - nominal, axis=1)) * scale)

    def _cell_levels(
        self, frame: np.ndarray, homography: np.ndarray, ids: list[int]
    ) -> tuple[np.ndarray, np.ndarray]:
        """The median black and white (per channel) of the markers' cells in `frame`."""
        centres = np.concatenate([self._cells[ident][0] for ident in ids])
        is_white = np.concatenate([self._cells[ident][1] for ident in ids])
        values = _sample(frame, _apply(np.linalg.inv(homography), centres))  # one pass, all ids
        return np.median(values[~is_white], axis=0), np.median(values[is_white], axis=0)

    def _levels(
        self, frame: np.ndarray, homography: np.ndarray, ids: list[int]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Per-channel gain and offset that map the markers' cells onto the workcell's."""
        dark, light = self._cell_levels(frame, homography, ids)
        contrast = light - dark
        if float(contrast.min()) < self.bounds.min_contrast:
            raise RegistrationError(
                f"{NOT_FOUND}: they are too faint to read the light: white - black "
                f"{contrast.min():.0f} levels (at least {self.bounds.min_contrast:.0f})"
            )
        gain = (self._white - self._black) / contrast
        return gain, self._black - gain * dark

    def measure_levels(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The markers' black and white in `frame` (per channel): a workcell's levels are
        measured so, on a frame at the nominal pose and light."""
        found = self._found(frame)
        return self._cell_levels(frame, self._fit(found)[0], sorted(found))


def to_table_frame(
    registration: Registration, images: np.ndarray | list[np.ndarray]
) -> tuple[np.ndarray, list[str | None]]:
    """What a model is given of each image, and why an image could not be registered (None
    where it was): an image at the model's size is taken as already in the table frame (a
    render, a registered image, a plan's own image); any other size is a camera frame and is
    registered. A frame that cannot be registered is resized as it is, so that the model can
    still say how far it lies from what it knows, and its reason is kept: it is not known."""
    size = registration.size
    out, reasons = [], []
    for image in images:
        reason = None
        if image.shape[:2] == (size, size):
            registered = np.ascontiguousarray(image)
        else:
            try:
                registered = registration.register(image).image
            except RegistrationError as exc:
                registered, reason = _resize(image, size), str(exc)
        out.append(registered)
        reasons.append(reason)
    return np.stack(out), reasons


def _cell_centres(marker_id: int, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Canonical-frame points inside every cell of a marker (a 3 x 3 grid over the middle half
    of each cell, away from the edges blurred by resampling), and whether each is white."""
    cells = marker_cells(marker_id)
    n = cells.shape[0]
    to_canonical = cv2.getPerspectiveTransform(_marker_square(n), corners.astype(np.float32))
    offsets = np.array([0.25, 0.5, 0.75])
    points, white = [], []
    for r in range(n):
        for c in range(n):
            for dy in offsets:
                for dx in offsets:
                    points.append((c + dx, r + dy))
                    white.append(bool(cells[r, c]))
    return _apply(to_canonical, np.array(points)), np.array(white)


def _apply(homography: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 2) points through a homography."""
    lifted = np.column_stack([points, np.ones(len(points))]) @ homography.T
    return lifted[:, :2] / lifted[:, 2:3]


def _scale(homography: np.ndarray, at: np.ndarray) -> float:
    """Canonical pixels per frame pixel near `at` (the square root of the local area ratio)."""
    square = at + np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float64)
    mapped = _apply(homography, square)
    x, y = mapped[:, 0], mapped[:, 1]
    area = 0.5 * abs(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1)))
    return float(np.sqrt(area))


def _rms(residuals: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(residuals**2, axis=1))))


def _sample(image: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 3) bilinear samples of `image` at (x, y) `points`; points outside are clamped."""
    h, w = image.shape[:2]
    x = np.clip(points[:, 0], 0, w - 1.001)
    y = np.clip(points[:, 1], 0, h - 1.001)
    x0, y0 = np.floor(x).astype(np.intp), np.floor(y).astype(np.intp)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    at = y0 * w + x0  # the four neighbours in one gather; only these converted, not the frame
    near = image.reshape(h * w, -1)[np.concatenate([at, at + 1, at + w, at + w + 1])]
    p00, p01, p10, p11 = near.astype(np.float64).reshape(4, len(at), -1)
    top = p00 * (1 - fx) + p01 * fx
    bottom = p10 * (1 - fx) + p11 * fx
    return top * (1 - fy) + bottom * fy


def _refine(gray: np.ndarray, quad: np.ndarray, cells: int) -> np.ndarray:
    """A marker's corners to sub-pixel precision on the whole frame, in a window one cell
    across (half a cell each side): the detector's own step (0.3 cell each side, at most 5 px,
    stopping at 0.1 px) leaves them where its threshold's outline began, up to a pixel apart
    for one frame searched whole or in windows; this one converges to the same corner from
    either, 0.43 px from the true corner at the median on box-stacking frames at `camera`
    (0.68 before)."""
    stop = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 0.001)

    def refined(start: np.ndarray, half: int) -> np.ndarray:
        return cv2.cornerSubPix(gray, start.copy(), (half, half), (-1, -1), stop)

    corners = np.ascontiguousarray(quad, dtype=np.float32).reshape(-1, 1, 2)
    half = _half_cell(corners, cells)
    for _ in range(3):  # the window is the refined corners' own
        corners = refined(corners, half)
        if _half_cell(corners, cells) == half:
            break
        half = _half_cell(corners, cells)
    # a cell's half near x.5 pixels: both windows may be the corners' own, and which one a
    # start reaches depends on the start; the larger one is taken, so that every start agrees
    if abs(0.5 * _module(corners, cells) - (half + 0.5)) < HALF_CELL_MARGIN:
        wider = refined(corners, half + 1)
        if _half_cell(wider, cells) == half + 1:
            corners = wider
    return corners.reshape(4, 2).astype(np.float64)


def _module(corners: np.ndarray, cells: int) -> float:
    """A cell's side (frame pixels) of the marker at `corners`."""
    outline = np.asarray(corners, np.float32).reshape(-1, 1, 2)
    return float(cv2.arcLength(outline, True)) / (4 * cells)


def _half_cell(corners: np.ndarray, cells: int) -> int:
    """Half a cell of the marker at `corners`, in whole pixels (at least 2)."""
    return max(2, round(0.5 * _module(corners, cells)))


def _reads(gray: np.ndarray, quads: np.ndarray, bits: np.ndarray, bounds: Bounds) -> np.ndarray:
    """Whether each marker at `quads` (M, 4, 2 frame corners) shows its `bits` (M, n, n): every
    cell's centre pixel on its side of the midpoint between its black and white cells' means,
    these at least `bounds.min_contrast` apart."""
    n = bits.shape[1]
    unit = _marker_square(n)
    to_frame = np.stack([cv2.getPerspectiveTransform(unit, q.astype(np.float32)) for q in quads])
    lifted = _cell_grid(n) @ to_frame.transpose(0, 2, 1)  # (M, n * n, 3)
    points = np.rint(lifted[..., :2] / lifted[..., 2:]).astype(int)
    x = np.clip(points[..., 0], 0, gray.shape[1] - 1)
    y = np.clip(points[..., 1], 0, gray.shape[0] - 1)
    values = gray[y, x].astype(np.float64)  # (M, n * n)
    white = bits.reshape(len(bits), -1)
    high = (values * white).sum(axis=1) / white.sum(axis=1)
    low = (values * ~white).sum(axis=1) / (~white).sum(axis=1)
    middle = (low + high) / 2
    darkest_white = np.where(white, values, np.inf).min(axis=1)
    lightest_black = np.where(white, -np.inf, values).max(axis=1)
    contrast = high - low >= bounds.min_contrast
    return contrast & (lightest_black < middle) & (middle < darkest_white)


def _marker_square(n: int) -> np.ndarray:
    """A marker of n x n cells' corners, in cells, in its corners' order."""
    return np.array([[0, 0], [n, 0], [n, n], [0, n]], np.float32)


@functools.cache
def _cell_grid(n: int) -> np.ndarray:
    """The centres of a marker's n x n cells, in cells, lifted: (n * n, 3)."""
    centres = np.stack(np.meshgrid(np.arange(n) + 0.5, np.arange(n) + 0.5), -1).reshape(-1, 2)
    return np.column_stack([centres, np.ones(len(centres))])


def _map_levels(image: np.ndarray, gain: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """uint8 `image` * gain + shift per channel, rounded and clipped: through a table of the
    256 levels per channel, the same numbers as computing every pixel."""
    levels = np.arange(256, dtype=np.float32)[:, None] * gain.astype(np.float32) + shift
    table = np.clip(np.rint(levels), 0, 255).astype(np.uint8)  # (256, 3)
    return cv2.LUT(np.ascontiguousarray(image), table.reshape(256, 1, 3))


def _resize(image: np.ndarray, size: int) -> np.ndarray:
    """To `size` x `size`: area averaging down (as a renderer's multisampling), linear up."""
    if image.shape[:2] == (size, size):
        return np.ascontiguousarray(image)
    flags = cv2.INTER_AREA if image.shape[0] > size else cv2.INTER_LINEAR
    return cv2.resize(image, (size, size), interpolation=flags)
