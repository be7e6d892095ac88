"""The rope-box world in MuJoCo physics: boxes pushed by a mocap weld dragging a flex rope, the
rope lifted over a pillar by a mocap hand, the state read back from where the boxes stand and
how the rope's vertices run past the pillars."""

from __future__ import annotations

import itertools
import math

import numpy as np

from services.sim.rendering import mujoco
from services.sim.rope_box.scene import RopeBoxGeometry, box_body, build_mjcf
from services.sim.workcell import CameraWorld, with_markers
from shared.tasks.base import InvalidStateError, World, WorldError
from shared.tasks.rope_box import BOXES, Cell, RopeBox, RopeBoxAction, RopeBoxState

SETTLE_MAX_SECONDS = 1.5
SETTLE_MIN_SECONDS = 0.1
SETTLE_SPEED = 0.01  # m/s: the rope and boxes count as at rest below this
PUSH_SPEED = 0.3  # m/s of a pushed box
PUSH_LIFT = 0.002  # m: a pushed box slides just clear of the floor
HAND_SPEED = 0.4  # m/s of the hand lifting the rope
LIFT_CLEARANCE = 0.012  # m of air between the hand and the pillar's top
LIFT_ACROSS = 0.3  # cells beyond the pillar where the lifted rope is laid down
LIFT_DRAW = 0.1  # cells the laid rope is drawn on along the floor
LIFT_NEAR = 0.25  # cells before the pillar where the rope is lifted
CLEARANCE = 0.0015  # m: a laid rope keeps this far from the pillars
PATH_TRIES = 100
BEND = 0.3  # cells from a pillar where a rope bent round it is laid


def swept_angles(points: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Angle swept round each centre (M, 2) by the polyline `points` (N, 2), radians,
    counter-clockwise positive."""
    rel = points[None, :, :] - centres[:, None, :]  # (M, N, 2)
    a, b = rel[:, :-1], rel[:, 1:]
    cross = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    dot = (a * b).sum(-1)
    return np.arctan2(cross, dot).sum(-1)


def _resample(path: np.ndarray, count: int) -> np.ndarray:
    """`count` points evenly spaced along the polyline `path`."""
    steps = np.linalg.norm(np.diff(path, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(steps)])
    at = np.linspace(0.0, s[-1], count)
    return np.column_stack([np.interp(at, s, path[:, k]) for k in range(2)])


def _segment_distance(points: np.ndarray, centre: np.ndarray) -> float:
    a, b = points[:-1], points[1:]
    d = b - a
    t = np.clip(((centre - a) * d).sum(1) / np.maximum((d * d).sum(1), 1e-12), 0, 1)
    return float(np.linalg.norm(a + t[:, None] * d - centre, axis=1).min())


class RopeBoxWorld(CameraWorld, World[RopeBoxState, RopeBoxAction]):
    # the camera looks straight down: the markers take the view's four corners
    marker_places = (
        (0, (-40.0, -40.0), 44.0),
        (1, (296.0, -40.0), 44.0),
        (2, (296.0, 296.0), 44.0),
        (3, (-40.0, 296.0), 44.0),
    )

    def __init__(
        self,
        task: RopeBox | None = None,
        image_size: int = 64,
        geometry: RopeBoxGeometry | None = None,
    ) -> None:
        self.task = task or RopeBox()
        self.image_size = image_size
        self.geometry = g = geometry or RopeBoxGeometry()
        self.relief_m = g.box_size  # the boxes; the pillars and a lifted rope stand lower
        xml = build_mjcf(self.task.config, g, image_size)
        self.model = mujoco.MjModel.from_xml_string(with_markers(xml, self.task.workcell))
        self.data = mujoco.MjData(self.model)
        self._open_cameras("top", image_size, self.task.workcell is not None)
        first = int(self.model.flex_vertadr[0])
        count = int(self.model.flex_vertnum[0])
        self._vertex_body = self.model.flex_vertbodyid[first : first + count].copy()
        self._body_origin = self.model.body_pos[self._vertex_body].copy()
        dof = self.model.body_dofadr[self._vertex_body]
        self._qpos = self.model.jnt_qposadr[self.model.dof_jntid[dof]][:, None] + np.arange(3)
        self._box = {b: self.model.body(box_body(b)).id for b in BOXES}
        self._box_qpos = {
            b: int(self.model.jnt_qposadr[self.model.body_jntadr[i]]) for b, i in self._box.items()
        }
        self._weld = {b: self.model.equality(f"grip_{b}").id for b in BOXES}
        for box, end in zip(BOXES, (0, count - 1), strict=True):
            eq = self.model.equality(f"end_{box}").id
            self.model.eq_obj2id[eq] = self._vertex_body[end]
            self.model.eq_data[eq, 3:6] = 0.0  # the vertex body's own origin
        self._hand = self.model.equality("hand").id
        self._grip = int(self.model.body("gripper").mocapid[0])
        n = self.task.config.size
        self._cells = np.array(
            [[g.cell_xy(r, c, n) for c in range(n)] for r in range(n)]
        )  # (n, n, 2)
        self._pillars = np.array(
            [g.cell_xy(p.row + 0.5, p.col + 0.5, n) for p in self.task.config.pillars]
        )

    # ----- geometry -----
    def _xy(self, cell: Cell) -> np.ndarray:
        return self._cells[cell.row, cell.col].copy()

    def vertices(self) -> np.ndarray:
        """(V, 3) rope vertex positions."""
        return self.data.xpos[self._vertex_body].copy()

    # ----- placing and settling -----
    def reset(self, state: RopeBoxState, rng: np.random.Generator) -> RopeBoxState:
        state = self.task.parse_state(self.task.state_to_json(state))
        mujoco.mj_resetData(self.model, self.data)
        g = self.geometry
        ends = []
        for box, cell in zip(BOXES, (state.green, state.orange), strict=True):
            xy = self._xy(cell) + rng.uniform(-g.noise, g.noise, 2)
            adr = self._box_qpos[box]
            self.data.qpos[adr : adr + 3] = (*xy, g.half + 1e-4)
            self.data.qpos[adr + 3 : adr + 7] = (1, 0, 0, 0)
            ends.append(xy)
        path = self._rope_path(state, ends[0], ends[1], rng)
        points = np.column_stack([path, np.full(len(path), g.rope_radius)])
        self.data.qpos[self._qpos] = points - self._body_origin
        mujoco.mj_forward(self.model, self.data)
        self._settle()
        return self.read_state()

    def _rope_path(
        self, state: RopeBoxState, a: np.ndarray, b: np.ndarray, rng: np.random.Generator
    ) -> np.ndarray:
        """Rope vertices (V, 2) from a to b running past the pillars as `state` says, its slack
        laid in random waves: the rope's shape is a nuisance, its way past the pillars not."""
        g = self.geometry
        length = self.task.config.rope_cells * g.cell
        base = [a]
        if state.rope:
            pillar = (state.rope - 1) // 2
            outward = self._side(state, pillar)
            bend = self._pillars[pillar] + BEND * g.cell * outward
            base.append(bend)
        base.append(b)
        clear = g.pillar_radius + g.rope_radius + CLEARANCE
        inside = self.task.config.size / 2 * g.cell - g.rope_radius  # on the grid
        for attempt in range(PATH_TRIES):
            if state.rope:  # the bend a little nearer or further round the pillar
                base[1] = bend + rng.uniform(-0.08, 0.12) * g.cell * outward
            waves = int(rng.integers(1, 5)) + attempt // 20
            path = self._with_slack(
                _resample(np.array(base), 200), length, waves, rng.choice([-1.0, 1.0])
            )
            if path is None:
                continue
            points = _resample(path, g.rope_vertices)
            if (
                np.abs(points).max() < inside
                and self._is_rope(state, points)
                and all(_segment_distance(points, p) > clear for p in self._pillars)
            ):
                return points
        raise WorldError(f"no rope path found for {self.task.state_label(state)}")

    @staticmethod
    def _with_slack(path: np.ndarray, length: float, waves: int, sign: float) -> np.ndarray | None:
        """`path` with a sideways wave of `waves` half-periods that makes it `length` long."""
        d = np.gradient(path, axis=0)
        normal = np.column_stack([-d[:, 1], d[:, 0]]) / np.linalg.norm(d, axis=1)[:, None]
        s = np.linspace(0.0, 1.0, len(path))
        shape = np.sin(np.pi * waves * s)[:, None] * normal * sign

        def total(h: float) -> float:
            return float(np.linalg.norm(np.diff(path + h * shape, axis=0), axis=1).sum())

        if total(0.0) > length:
            return None
        lo, hi = 0.0, length
        for _ in range(40):
            mid = (lo + hi) / 2
            lo, hi = (mid, hi) if total(mid) < length else (lo, mid)
        return path + lo * shape

    def _settle(self) -> None:
        dt = self.model.opt.timestep
        for step in range(int(SETTLE_MAX_SECONDS / dt)):
            mujoco.mj_step(self.model, self.data)
            if step * dt > SETTLE_MIN_SECONDS and np.abs(self.data.qvel).max() < SETTLE_SPEED:
                break

    # ----- looking -----
    def _rope_code(self, green: Cell, orange: Cell, points: np.ndarray) -> int:
        """The rope code of vertices (V, 2) between boxes in these cells: the swept angles of
        the path from the green cell's centre along the rope to the orange one's."""
        path = np.vstack([self._xy(green), points, self._xy(orange)])
        return self.task.rope_from_swept(green, orange, swept_angles(path, self._pillars))

    def _is_rope(self, state: RopeBoxState, points: np.ndarray) -> bool:
        try:
            return self._rope_code(state.green, state.orange, points) == state.rope
        except InvalidStateError:  # round two pillars, or stretched
            return False

    def read_state(self) -> RopeBoxState:
        g, n = self.geometry, self.task.config.size
        cells = []
        for box in BOXES:
            pos = self.data.xpos[self._box[box]]
            rot = self.data.xmat[self._box[box]].reshape(3, 3)
            if np.abs(rot[2]).max() < math.cos(math.radians(20)):
                raise WorldError(f"box {box!r} is tilted, not standing on a face")
            offset = (pos[:2] - self._cells.reshape(-1, 2)) / g.cell
            index = int(np.argmin(np.abs(offset).max(axis=1)))
            if np.abs(offset[index]).max() > 0.3 or abs(pos[2] - g.half) > 0.25 * g.box_size:
                raise WorldError(f"box {box!r} at {pos.round(3).tolist()} is in no cell")
            cells.append(Cell(*divmod(index, n)))
        points = self.vertices()
        if points[:, 2].max() > g.pillar_height:  # resting on a pillar's top
            raise WorldError("the rope is not lying on the floor")
        green, orange = cells
        try:
            rope = self._rope_code(green, orange, points[:, :2])
            return self.task.parse_state(self.task.state_to_json(RopeBoxState(green, orange, rope)))
        except InvalidStateError as exc:
            raise WorldError(f"the scene is no state: {exc}") from None

    # ----- acting -----
    def execute(self, action: RopeBoxAction, rng: np.random.Generator) -> RopeBoxState:
        state = self.read_state()
        self.task.check_action(state, action)  # raises before anything moves
        if action.kind == "box":
            self._push(BOXES[0] if action.pick == state.green else BOXES[1], action, rng)
        else:
            self._lift(state, self.task.config.pillars.index(action.pick))
        self._settle()
        return self.read_state()

    def _push(self, box: str, action: RopeBoxAction, rng: np.random.Generator) -> None:
        g = self.geometry
        body = self._box[box]
        start = self.data.xpos[body].copy()
        target = np.array([*self._xy(action.release), g.half + PUSH_LIFT])
        target[:2] += rng.uniform(-g.noise, g.noise, 2)
        lifted = np.array([*start[:2], g.half + PUSH_LIFT])
        self.data.mocap_pos[self._grip] = start
        self.data.mocap_quat[self._grip] = (1, 0, 0, 0)
        self.data.eq_active[self._weld[box]] = 1
        self._move(start, lifted, PUSH_SPEED)
        self._move(lifted, target, PUSH_SPEED)
        self._hold(0.05)
        self.data.eq_active[self._weld[box]] = 0

    def _side(self, state: RopeBoxState, pillar: int) -> np.ndarray:
        """Unit vector from the pillar to where the rope of `state` passes it."""
        a, b = self._xy(state.green), self._xy(state.orange)
        centre = self._pillars[pillar]
        if state.rope and (state.rope - 1) // 2 == pillar:
            along = (b - a) / np.linalg.norm(b - a)
            side = np.array([along[1], -along[0]])  # the rope's right: the pillar on its left
            return side if (state.rope - 1) % 2 == 0 else -side
        t = np.clip((centre - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
        side = a + t * (b - a) - centre
        return side / np.linalg.norm(side)

    def _lift(self, state: RopeBoxState, pillar: int) -> None:
        """Take the rope at its middle (the most rope to either box), draw it along the floor
        to the pillar's side the rope leaves, lift it clear of the pillar's top, carry it
        across and lay it down on the side the rope goes to, as a hand would."""
        g = self.geometry
        vertex = len(self._vertex_body) // 2
        start = self.vertices()[vertex]
        centre = self._pillars[pillar]
        after = self.task.apply(
            state, RopeBoxAction("rope", *(self.task.config.pillars[pillar],) * 2)
        )
        away = self._side(after, pillar)
        near = np.array([*(centre - LIFT_NEAR * g.cell * away), g.rope_radius])
        high = g.pillar_height + LIFT_CLEARANCE
        down = np.array([*(centre + LIFT_ACROSS * g.cell * away), g.rope_radius])
        # laid down, drawn a little further: a rope resting on the pillar's top slides off
        drawn = down + np.array([*(LIFT_DRAW * g.cell * away), 0.0])
        self._carry(vertex, [start, near, [*near[:2], high], [*down[:2], high], down, drawn])
        self._settle()
        points = self.vertices()
        top = int(np.argmax(points[1:-1, 2])) + 1  # (the ends are tied under the boxes)
        if points[top, 2] > g.pillar_height:  # caught on a pillar's top: drawn off it, once
            off = np.array([*(points[top, :2] + 2 * LIFT_DRAW * g.cell * away), g.rope_radius])
            self._carry(top, [points[top], [*off[:2], points[top, 2]], off])

    def _carry(self, vertex: int, way: list) -> None:
        """The hand holds a rope vertex along the waypoints, then lets go."""
        self.data.mocap_pos[self._grip] = way[0]
        self.model.eq_obj2id[self._hand] = self._vertex_body[vertex]
        self.model.eq_data[self._hand, :6] = 0.0
        self.data.eq_active[self._hand] = 1
        for a, b in itertools.pairwise(way):
            self._move(np.asarray(a), np.asarray(b), HAND_SPEED)
        self._hold(0.05)
        self.data.eq_active[self._hand] = 0

    def _move(self, a: np.ndarray, b: np.ndarray, speed: float) -> None:
        steps = max(1, int(np.ceil(np.linalg.norm(b - a) / (speed * self.model.opt.timestep))))
        for t in np.linspace(0, 1, steps + 1)[1:]:
            self.data.mocap_pos[self._grip] = a + t * (b - a)
            mujoco.mj_step(self.model, self.data)

    def _hold(self, seconds: float) -> None:
        for _ in range(int(seconds / self.model.opt.timestep)):
            mujoco.mj_step(self.model, self.data)

    def action_pixels(
        self, action: RopeBoxAction
    ) -> tuple[tuple[float, float], tuple[float, float]]:
        n = self.task.config.size
        if action.kind == "rope":
            p = action.pick
            pixel = self.to_pixel(np.array(self.geometry.cell_xy(p.row + 0.5, p.col + 0.5, n)))
            return pixel, pixel
        return self.to_pixel(self._xy(action.pick)), self.to_pixel(self._xy(action.release))

    def to_pixel(self, xy: np.ndarray) -> tuple[float, float]:
        """Where a table point appears in the rendered image, (x, y) pixels."""
        g = self.geometry
        focal = self.image_size / 2 / math.tan(math.radians(g.fovy) / 2)
        height = g.camera_height()
        return (
            self.image_size / 2 + focal * xy[0] / height,
            self.image_size / 2 - focal * xy[1] / height,
        )
