"""The box-stacking world in MuJoCo physics: place, settle, look, carry with a mocap weld."""

from __future__ import annotations

import itertools
from collections.abc import Mapping

import numpy as np

from services.sim.box_stacking.scene import (
    BOX_LOOKS,
    SceneGeometry,
    box_body,
    build_mjcf,
    grip_weld,
)
from services.sim.rendering import mujoco
from services.sim.workcell import CameraWorld, with_markers
from shared.tasks.base import World, WorldError
from shared.tasks.box_stacking import BoxStacking, Move, Stacks

SETTLE_MAX_STEPS = 250
SETTLE_SPEED = 2e-3  # m/s and rad/s below which the boxes count as at rest
CARRY_SPEED = 0.8  # m/s of the gripper
CARRY_CLEARANCE = 0.02  # m of air between the carried box and the stacks it passes
RELEASE_GAP = 0.002  # m above the resting height when the weld lets go
MAX_TILT_COS = np.cos(np.deg2rad(20))


class BoxStackingWorld(CameraWorld, World[Stacks, Move]):
    # The camera looks at the table obliquely: the markers lie low, where the table is near,
    # the near ones below the view, clear of the frame's edge where perspective widens them;
    # all four are needed (with three, the far edge of the view is 13-17 px off).
    marker_places = (
        (0, (-40.0, 190.0), 44.0),
        (1, (296.0, 190.0), 44.0),
        (2, (208.0, 302.0), 44.0),
        (3, (48.0, 302.0), 44.0),
    )
    min_markers = 4

    def __init__(
        self,
        task: BoxStacking | None = None,
        image_size: int = 64,
        geometry: SceneGeometry | None = None,
        box_looks: Mapping[str, str] = BOX_LOOKS,
    ) -> None:
        self.task = task or BoxStacking()
        self.image_size = image_size
        self.geometry = geometry or SceneGeometry()
        self.relief_m = self.task.config.levels * self.geometry.box_size  # a full column
        cfg = self.task.config
        mjcf = build_mjcf(cfg, self.geometry, image_size, box_looks)
        mjcf = with_markers(mjcf, self.task.workcell)
        self.model = mujoco.MjModel.from_xml_string(mjcf)
        self.data = mujoco.MjData(self.model)
        self._open_cameras("front", image_size, self.task.workcell is not None)
        self._column_x = np.array(
            [self.geometry.column_x(c, cfg.columns) for c in range(cfg.columns)]
        )
        self._qpos_adr = {}
        self._qvel_adr = {}
        self._body = {}
        self._weld = {}
        for box in cfg.boxes:
            body = self.model.body(box_body(box))
            joint = self.model.jnt_bodyid.tolist().index(body.id)
            self._qpos_adr[box] = int(self.model.jnt_qposadr[joint])
            self._qvel_adr[box] = int(self.model.jnt_dofadr[joint])
            self._body[box] = body.id
            self._weld[box] = self.model.equality(grip_weld(box)).id
        self._mocap = int(self.model.body("gripper").mocapid[0])

    # ----- placing and settling -----
    def _cell_position(self, row: int, col: int, rng: np.random.Generator) -> np.ndarray:
        dx, dy = rng.uniform(-self.geometry.noise, self.geometry.noise, size=2)
        return np.array([self._column_x[col] + dx, dy, self.geometry.level_z(row)])

    def reset(self, state: Stacks, rng: np.random.Generator) -> Stacks:
        state = self.task.parse_state(self.task.state_to_json(state))
        mujoco.mj_resetData(self.model, self.data)  # no warm-start carried between resets
        for col, column in enumerate(state):
            for row, box in enumerate(column):
                pos = self._cell_position(row, col, rng)
                pos[2] += 1e-4 * (row + 1)  # a hair of clearance: no initial penetration
                adr = self._qpos_adr[box]
                self.data.qpos[adr : adr + 3] = pos
                self.data.qpos[adr + 3 : adr + 7] = (1, 0, 0, 0)
        mujoco.mj_forward(self.model, self.data)
        self._settle()
        return self.read_state()

    def _settle(self) -> None:
        for step in range(SETTLE_MAX_STEPS):
            mujoco.mj_step(self.model, self.data)
            if step > 10 and np.abs(self.data.qvel).max() < SETTLE_SPEED:
                break

    # ----- looking -----
    def read_state(self) -> Stacks:
        g, cfg = self.geometry, self.task.config
        cells: list[list[tuple[int, str]]] = [[] for _ in range(cfg.columns)]
        for box in cfg.boxes:
            pos = self.data.xpos[self._body[box]]
            rot = self.data.xmat[self._body[box]].reshape(3, 3)
            if np.abs(rot[2]).max() < MAX_TILT_COS:  # no box axis near vertical: tipped over
                raise WorldError(f"box {box!r} is tilted, not standing on a face")
            col = int(np.argmin(np.abs(self._column_x - pos[0])))
            if (
                abs(pos[0] - self._column_x[col]) > g.column_spacing / 2 - g.half
                or abs(pos[1]) > g.box_size
            ):
                raise WorldError(f"box {box!r} at x={pos[0]:.3f}, y={pos[1]:.3f} is in no column")
            row = round((pos[2] - g.half) / g.box_size)
            if not 0 <= row < cfg.levels or abs(pos[2] - g.level_z(row)) > 0.25 * g.box_size:
                raise WorldError(f"box {box!r} at height {pos[2]:.3f} is at no level")
            cells[col].append((row, box))
        stacks = []
        for col, column in enumerate(cells):
            column.sort()
            rows = [row for row, _ in column]
            if rows != list(range(len(rows))):
                raise WorldError(f"column {col} has boxes at levels {rows}: not a stack")
            stacks.append([box for _, box in column])
        return self.task.parse_state({"stacks": stacks})

    # ----- acting -----
    def execute(self, action: Move, rng: np.random.Generator) -> Stacks:
        state = self.read_state()
        self.task.check_action(state, action)  # raises before anything moves
        box = state[action.pick.col][-1]
        body, weld = self._body[box], self._weld[box]
        start = self.data.xpos[body].copy()
        target = self._cell_position(action.release.row, action.release.col, rng)
        target[2] += RELEASE_GAP
        # Clear every column on the way; the carried box's own column is one lower now.
        lo, hi = sorted((action.pick.col, action.release.col))
        tallest = max(len(state[c]) - (c == action.pick.col) for c in range(lo, hi + 1))
        safe_z = self.geometry.level_z(tallest) + CARRY_CLEARANCE

        self.data.mocap_pos[self._mocap] = start
        self.data.mocap_quat[self._mocap] = self.data.xquat[body]
        self.data.eq_active[weld] = 1
        waypoints = [start, [*start[:2], safe_z], [*target[:2], safe_z], target]
        for a, b in itertools.pairwise(waypoints):
            self._move_gripper(np.asarray(a), np.asarray(b))
        for _ in range(25):  # let the weld catch up before letting go
            mujoco.mj_step(self.model, self.data)
        self.data.eq_active[weld] = 0
        self._settle()
        return self.read_state()

    def _move_gripper(self, a: np.ndarray, b: np.ndarray) -> None:
        step_length = CARRY_SPEED * self.model.opt.timestep
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / step_length)))
        for t in np.linspace(0, 1, n + 1)[1:]:
            self.data.mocap_pos[self._mocap] = a + t * (b - a)
            mujoco.mj_step(self.model, self.data)

    def action_pixels(self, action: Move) -> tuple[tuple[float, float], tuple[float, float]]:
        return self.cell_pixel(*action.pick), self.cell_pixel(*action.release)

    def cell_pixel(self, row: int, col: int) -> tuple[float, float]:
        """Where the centre of a grid cell appears in the image (x right, y down, pixels)."""
        cam = self.model.camera("front")
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_camlight(self.model, self.data)
        point = np.array([self._column_x[col], 0.0, self.geometry.level_z(row)])
        rotation = self.data.cam_xmat[cam.id].reshape(3, 3)
        x, y, z = rotation.T @ (point - self.data.cam_xpos[cam.id])
        focal = self.image_size / 2 / np.tan(np.deg2rad(self.model.cam_fovy[cam.id]) / 2)
        return self.image_size / 2 + focal * x / -z, self.image_size / 2 - focal * y / -z
