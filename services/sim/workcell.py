"""The workcell in MuJoCo: marker geoms on the table and the camera frame that sees them.

The canonical view (each scene's named camera, the frame of the actions) stays what it always
was; the cell's camera sees more of the table round it, where the markers lie, so that nothing
the robot moves ever covers them. `FrameCamera` renders that wider frame from the same camera
pose: the same focal length, `FRAME_SCALE` times the field of view, so that at the nominal pose
the canonical view is its middle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from services.sim.rendering import OffscreenCamera, mujoco
from shared.registration import Registration, RegistrationError, to_table_frame
from shared.tasks.base import World
from shared.workcell import FRAME_SCALE, FRAME_SIZE, CellCamera, Marker, Workcell, marker_cells

WHITE = "0.93 0.93 0.93 1"
BLACK = "0.03 0.03 0.03 1"
BASE_M = 0.0006  # the printed sheet's thickness on the table


def marker_geoms(workcell: Workcell | None) -> str:
    """MJCF geoms of every marker (a white sheet with a quiet margin of one cell, black cells
    on it), static and without contacts: they change no physics."""
    if workcell is None:
        return ""
    parts = []
    for marker in workcell.markers:
        cells = marker_cells(marker.id)
        n = cells.shape[0]
        side = marker.side_mm / 1000
        cell = side / n
        cx, cy = (v / 1000 for v in marker.centre_mm)
        base = side / 2 + cell
        parts.append(
            f'<geom name="marker_{marker.id}" type="box" pos="{cx:.5f} {cy:.5f} {BASE_M / 2}" '
            f'size="{base:.5f} {base:.5f} {BASE_M / 2}" rgba="{WHITE}" contype="0" '
            'conaffinity="0" group="2"/>'
        )
        for r in range(n):
            for c in range(n):
                if cells[r, c]:
                    continue
                x = cx - side / 2 + (c + 0.5) * cell
                y = cy + side / 2 - (r + 0.5) * cell  # row 0 is the marker's top (+y)
                parts.append(
                    f'<geom type="box" pos="{x:.5f} {y:.5f} {BASE_M + 0.0001}" '
                    f'size="{cell / 2:.5f} {cell / 2:.5f} 0.0001" rgba="{BLACK}" contype="0" '
                    'conaffinity="0" group="2"/>'
                )
    return "".join(parts)


def with_markers(xml: str, workcell: Workcell | None) -> str:
    """A scene's MJCF with the markers on its table."""
    if workcell is None:
        return xml
    return xml.replace("</worldbody>", marker_geoms(workcell) + "</worldbody>", 1)


class FrameCamera(OffscreenCamera):
    """The cell's camera: the named camera's pose, `scale` times its field of view."""

    def __init__(
        self, model: mujoco.MjModel, camera: str, size: int = FRAME_SIZE, scale: float = FRAME_SCALE
    ) -> None:
        offscreen = model.vis.global_  # the frame may be larger than the scene's own renders
        offscreen.offwidth = max(int(offscreen.offwidth), size)
        offscreen.offheight = max(int(offscreen.offheight), size)
        super().__init__(model, camera, size)
        self.model = model
        self._id = model.camera(camera).id
        half = math.radians(float(model.cam_fovy[self._id])) / 2
        self.fovy = math.degrees(2 * math.atan(scale * math.tan(half)))

    def render(self, data: mujoco.MjData) -> np.ndarray:
        canonical = float(self.model.cam_fovy[self._id])
        self.model.cam_fovy[self._id] = self.fovy
        try:
            return super().render(data)
        finally:
            self.model.cam_fovy[self._id] = canonical


class CameraWorld:
    """What every MuJoCo world does with its camera: the canonical view the models see and, in
    a cell with markers, the cell camera's wider frame of the same pose. A world calls
    `_open_cameras` once its model is loaded."""

    model: mujoco.MjModel
    data: mujoco.MjData
    camera: OffscreenCamera
    frame_camera: FrameCamera | None

    def _open_cameras(self, name: str, image_size: int, workcell: bool) -> None:
        self.camera = OffscreenCamera(self.model, name, image_size)
        self.frame_camera = FrameCamera(self.model, name) if workcell else None

    def render(self) -> np.ndarray:
        return self.camera.render(self.data)

    def frame(self) -> np.ndarray:
        if self.frame_camera is None:
            return self.render()
        return self.frame_camera.render(self.data)

    def close(self) -> None:
        self.camera.close()
        if self.frame_camera is not None:
            self.frame_camera.close()


@dataclass(frozen=True)
class Pinhole:
    """A MuJoCo camera as a pinhole of the canonical frame: project and back-project."""

    position: np.ndarray  # (3,) world
    axes: np.ndarray  # (3, 3) rows: x right, y up, z backwards (MuJoCo's camera frame)
    focal: float  # pixels of the canonical frame
    frame: int

    @classmethod
    def of(
        cls, model: mujoco.MjModel, data: mujoco.MjData, camera: str, frame: int = 256
    ) -> Pinhole:
        mujoco.mj_forward(model, data)
        cid = model.camera(camera).id
        fovy = math.radians(float(model.cam_fovy[cid]))
        return cls(
            position=data.cam_xpos[cid].copy(),
            axes=data.cam_xmat[cid].reshape(3, 3).T.copy(),
            focal=frame / 2 / math.tan(fovy / 2),
            frame=frame,
        )

    def project(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) world points -> (N, 2) (x, y) canonical pixels (pixel 0 spans 0..1)."""
        local = (np.atleast_2d(points) - self.position) @ self.axes.T
        depth = -local[:, 2]
        half = self.frame / 2
        return np.stack(
            [half + self.focal * local[:, 0] / depth, half - self.focal * local[:, 1] / depth],
            axis=1,
        )

    def to_frame(
        self, points: np.ndarray, size: int = FRAME_SIZE, scale: float = FRAME_SCALE
    ) -> np.ndarray:
        """(N, 3) world points -> (N, 2) OpenCV pixels of the cell's frame seen from here."""
        ratio = size / (self.frame * scale)
        return size / 2 + (self.project(points) - self.frame / 2) * ratio - 0.5

    def on_table(self, pixel: tuple[float, float]) -> tuple[np.ndarray, float]:
        """The table point (z = 0) seen at canonical `pixel`, and its depth along the axis."""
        half = self.frame / 2
        x, y = (pixel[0] - half) / self.focal, -(pixel[1] - half) / self.focal
        ray = self.axes.T @ np.array([x, y, -1.0])
        t = -self.position[2] / ray[2]
        return self.position + t * ray, float(t)


def design(
    pinhole: Pinhole, places: list[tuple[int, tuple[float, float], float]]
) -> tuple[Marker, ...]:
    """Markers at canonical-frame `places` (id, centre pixel, width in canonical pixels there):
    each a square on the table, sized to look that wide, rounded to the millimetre."""
    markers = []
    for ident, pixel, width in places:
        centre, depth = pinhole.on_table(pixel)
        side_mm = round(1000 * width * depth / pinhole.focal)
        cx, cy = (round(1000 * float(v)) for v in centre[:2])
        markers.append(table_marker(pinhole, ident, (cx, cy), side_mm))
    return tuple(markers)


def table_marker(
    pinhole: Pinhole, ident: int, centre_mm: tuple[float, float], side_mm: float
) -> Marker:
    """A marker lying on the table, its corners seen by the canonical camera."""
    cx, cy, h = centre_mm[0] / 1000, centre_mm[1] / 1000, side_mm / 2000
    z = BASE_M + 0.0002  # the printed face
    corners = np.array(
        [[cx - h, cy + h, z], [cx + h, cy + h, z], [cx + h, cy - h, z], [cx - h, cy - h, z]]
    )
    pixels = pinhole.project(corners) - 0.5  # OpenCV's pixels: pixel centres at integers
    return Marker(
        id=ident,
        centre_mm=(float(centre_mm[0]), float(centre_mm[1])),
        side_mm=float(side_mm),
        corners=tuple((float(x), float(y)) for x, y in pixels),
    )


def layout(world: World) -> Workcell:
    """The task's workcell designed from its world's canonical camera, calibrated on a clean
    frame at the nominal pose (rendered with the markers in place), as a cell is calibrated
    once: the corners where the detector finds them, taken to the canonical frame through the
    nominal camera, so that the detector's own bias (its corners lie about half a frame pixel
    inside the printed ones) cancels rather than tilting every homography; and the levels the
    markers' cells take."""
    name = world.task.name
    camera = world.camera.camera
    if not world.marker_places:
        raise ValueError(f"{name}: its world declares no marker places")
    designed = design(Pinhole.of(world.model, world.data, camera), list(world.marker_places))
    drafted = Workcell(markers=designed)
    scene = type(world)(world.task.with_workcell(drafted), image_size=world.image_size)
    try:
        scene.reset(scene.task.all_states()[0], np.random.default_rng(0))
        frame = scene.frame()
    finally:
        scene.close()
    found = Registration(drafted, world.image_size).detect(frame)
    missing = [m.id for m in designed if m.id not in found]
    if missing:
        raise ValueError(f"{name}: markers {missing} not found in the clean frame")
    size = frame.shape[0]
    scale = drafted.frame * FRAME_SCALE / size  # canonical pixels per frame pixel, nominally
    markers = tuple(
        replace(
            m,
            corners=tuple(
                (round(float(x), 3), round(float(y), 3))
                for x, y in (found[m.id] + 0.5 - size / 2) * scale + drafted.frame / 2 - 0.5
            ),
        )
        for m in designed
    )
    calibrated = Workcell(markers=markers)
    black, white = Registration(calibrated, world.image_size).measure_levels(frame)
    return Workcell(
        markers=markers,
        min_markers=world.min_markers,
        black=tuple(round(float(v), 2) for v in black),  # type: ignore[arg-type]
        white=tuple(round(float(v), 2) for v in white),  # type: ignore[arg-type]
        camera=cell_camera(world),
        relief_mm=round(world.relief_m * 1000, 2),
    )


def cell_camera(world: World) -> CellCamera:
    """The cell camera of a world: its frames' field of view (FRAME_SCALE times the canonical
    camera's, in the tangent of the half-angle) and its nominal centre, table millimetres (the
    table's top is the world's z = 0)."""
    nominal = Pinhole.of(world.model, world.data, world.camera.camera)
    half = math.atan(FRAME_SCALE * nominal.frame / 2 / nominal.focal)
    x, y, z = (round(float(v) * 1000, 2) for v in nominal.position)
    return CellCamera(fov_deg=round(math.degrees(2 * half), 4), centre_mm=(x, y, z))


def true_homography(moved: Pinhole, nominal: Pinhole) -> np.ndarray:
    """Frame pixels of a camera at `moved` -> canonical pixels of `nominal`, exact for points
    on the table: what a registration of that frame should find."""
    import cv2

    grid = np.stack(np.meshgrid(np.linspace(-0.5, 0.5, 11), np.linspace(-0.5, 0.5, 11)), -1)
    points = np.column_stack([grid.reshape(-1, 2), np.zeros(121)])
    near = points[(nominal.position - points) @ nominal.axes[2] > 0.05]  # in front of it
    homography, _ = cv2.findHomography(moved.to_frame(near), nominal.project(near) - 0.5, 0)
    return homography


class Observer:
    """What a model is given of what a world shows: at `clean`, or for a task without
    markers, the canonical render (the camera sits at the nominal pose, which registering its
    frame would only approximate); at other levels, the cell's frame registered to the table
    frame. `see()` raises RegistrationError when the frame's markers are not found.
    `register` False gives the cell camera's frames as they are, at every level, for a
    client whose server registers them (a robot over the public API). `moving`: a camera on a
    robot's head, its pose drawn anew (`relook(camera_only=True)`) before every look."""

    def __init__(self, world: World, register: bool = True, moving: bool = False) -> None:
        self.world = world
        self.register = register
        self.moving = moving
        workcell = world.task.workcell
        appearance = getattr(world, "appearance", None)  # an AppearanceWorld's level
        self.registration = None if workcell is None else Registration(workcell, world.image_size)
        clean = appearance is None or appearance.is_clean
        self.frames = self.registration is not None and (not clean or not register)

    def see(self) -> np.ndarray:
        image, why = self.look()
        if why is not None:
            raise RegistrationError(why)
        return image

    def look(self) -> tuple[np.ndarray, str | None]:
        """What the camera shows in the table frame and None, or, when its markers are not
        found, the frame only resized (to show, never to plan from) and why."""
        if self.moving and hasattr(self.world, "relook"):
            self.world.relook(camera_only=True)
        if not self.frames:
            return self.world.render(), None
        if not self.register:
            return self.world.frame(), None
        assert self.registration is not None
        image, (why,) = to_table_frame(self.registration, [self.world.frame()])
        return image[0], why

    def table_frame(self, image: np.ndarray) -> np.ndarray:
        """An image given from outside (a goal): at the model's size as it is, else a frame
        registered (RegistrationError when it cannot be)."""
        if self.registration is None or not self.register:
            return image
        (registered,), (why,) = to_table_frame(self.registration, [image])  # the one size rule
        if why is not None:
            raise RegistrationError(why)
        return registered
