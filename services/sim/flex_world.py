"""What every flex-cloth world shares: a MuJoCo flex on a table under a top-down camera.

Pixels of the task's action frame map to the table through the camera; resets load a settled
physics state from the library (`services.sim.settled`) and put it down at a fresh pose; the
state is read back by aligning the vertices rigidly with each state's ideal cloth. Subclasses
give the MJCF, the ideal cloths, the fold orders that resets draw and how an action moves the
cloth (`_carry`).
"""

from __future__ import annotations

import hashlib
import json
from abc import abstractmethod
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from services.sim.rendering import mujoco
from services.sim.settled import SettledLibrary
from services.sim.workcell import CameraWorld, with_markers
from shared.deadlines import check_deadline
from shared.tasks.base import InvalidActionError, World, WorldError
from shared.tasks.folding import ClothAction, FoldingTask, Folds, Pixel

SETTLE_MAX_SECONDS = 1.2
SETTLE_MIN_SECONDS = 0.15
SETTLE_SPEED = 0.02  # m/s: the cloth counts as at rest below this
# A settled cloth moved rigidly (its warm start kept) is at rest at once: under 0.3 mm in 20
# steps, so two steps show it. Walks of data generation whose move wrecked the cloth (about 1%,
# a top-layer pick where three flap tips meet): 2 of 230 with two steps, 1 of 170 with 12.
RESETTLE_MIN_SECONDS = 0.0
FAR = 0.03  # m: a vertex this far from a state's reference cloth does not match it
CLICK_NOISE = 1.5  # pixels (standard deviation, clipped at 2x) of a demonstrator's clicks
RESET_SHIFT = 0.003  # m, uniform, of the flat cloth that reset() starts from
RESET_TURN = np.deg2rad(1.0)
PERTURB_SHIFT = 0.005  # m, uniform: the no-action perturbation (paper: "slightly perturbing")
PERTURB_TURN = np.deg2rad(2.0)


class FlexWorld(CameraWorld, World[Folds, ClothAction]):
    episode_length = 10  # tuples walked from a reset: folded states come from physics
    settles = True
    # the folding cameras look straight down: the markers take the view's four corners
    marker_places = (
        (0, (-40.0, -40.0), 44.0),
        (1, (296.0, -40.0), 44.0),
        (2, (296.0, 296.0), 44.0),
        (3, (-40.0, 296.0), 44.0),
    )
    task: FoldingTask
    radius: float  # flex collision radius: the flat cloth lies at z = radius

    def __init__(
        self,
        task: FoldingTask,
        image_size: int,
        xml: str,
        assets: dict[str, bytes],
        flat: np.ndarray,
        triangles: np.ndarray,
        library: Sequence[Path] | None = None,
    ) -> None:
        """`flat`: (V, 2) vertex positions of the flat cloth, in metres about the frame's centre;
        `library`: the folders searched for this scene's settled states (default: the shipped
        models', then the cache); without one, each state is folded once, on first use."""
        self.task = task
        self.image_size = image_size
        self.model = mujoco.MjModel.from_xml_string(with_markers(xml, task.workcell), assets)
        self.data = mujoco.MjData(self.model)
        self._open_cameras("top", image_size, task.workcell is not None)
        first = int(self.model.flex_vertadr[0])
        count = int(self.model.flex_vertnum[0])
        self._vertex_body = self.model.flex_vertbodyid[first : first + count].copy()
        self._flat = flat
        self._triangles = triangles
        self._ring: list[set[int]] = [set() for _ in flat]
        for triangle in triangles.tolist():
            for v in triangle:
                self._ring[v].update(triangle)
        self._body_origin = self.model.body_pos[self._vertex_body].copy()
        dof = self.model.body_dofadr[self._vertex_body]
        xyz = np.arange(3)  # 3 slides a vertex
        self._qpos = self.model.jnt_qposadr[self.model.dof_jntid[dof]][:, None] + xyz
        self._dof = dof[:, None] + xyz
        lying = np.full(len(flat), self.radius)  # the flat cloth lies at z = radius
        self._flat_points = np.column_stack([flat, lying])
        self._grip = int(self.model.body("gripper").mocapid[0])
        self._references = {s: self._reference(s) for s in self.task.all_states()}
        cam = self.model.camera("top")
        self._camera_height = float(self.model.cam_pos[cam.id][2])
        fovy = float(self.model.cam_fovy[cam.id])
        self._focal = self.task.frame / 2 / np.tan(np.deg2rad(fovy) / 2)
        self.library = SettledLibrary.find(self.task, self.scene_hash(), library)
        self._steps = 0  # physics steps taken, for the deadline checks

    # ----- what a cloth world defines -----
    @abstractmethod
    def _reference(self, state: Folds) -> np.ndarray:
        """(V, 2) vertex positions of the ideal cloth in `state`."""

    @abstractmethod
    def _scene(self) -> tuple[str, dict[str, Any], dict[str, Any]]:
        """(physics MJCF, motion recipe, the shape's parameters): what shapes a settled cloth."""

    @abstractmethod
    def reset_orders(self, state: Folds) -> list[tuple[ClothAction, ...]]:
        """The fold orders that reach `state` from the flat cloth: resets draw one."""

    @abstractmethod
    def _carry(self, action: ClothAction) -> None:
        """Carry out a matched move physically; InvalidActionError when the pick misses."""

    # ----- frames: metres on the table <-> pixels of the task's action frame -----
    def to_pixels(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) world points -> (N, 2) continuous (col, row) in the action frame."""
        points = np.atleast_2d(points)
        depth = self._camera_height - points[:, 2]
        half = self.task.frame / 2
        return np.stack(
            [half + self._focal * points[:, 0] / depth, half - self._focal * points[:, 1] / depth],
            axis=1,
        )

    def to_table(self, pixel: Pixel, z: float = 0.0) -> np.ndarray:
        """The point at height z seen at the centre of `pixel`."""
        half = self.task.frame / 2
        depth = self._camera_height - z
        x = (pixel.col + 0.5 - half) * depth / self._focal
        y = -(pixel.row + 0.5 - half) * depth / self._focal
        return np.array([x, y, z])

    def action_pixels(self, action: ClothAction) -> tuple[tuple[float, float], tuple[float, float]]:
        """Pick and release in this world's image: the action frame scaled to the image size."""
        scale = self.image_size / self.task.frame
        pick, release = action.pick, action.release
        return (
            ((pick.col + 0.5) * scale, (pick.row + 0.5) * scale),
            ((release.col + 0.5) * scale, (release.row + 0.5) * scale),
        )

    # ----- vertices -----
    def vertices(self) -> np.ndarray:
        return self.data.flexvert_xpos.copy()

    def _set_vertices(
        self,
        positions: np.ndarray,
        velocities: np.ndarray | None = None,
        warmstart: np.ndarray | None = None,
    ) -> None:
        """Place the vertices (at rest unless `velocities` are given); a `warmstart` (the
        solver's last accelerations) lets a cloth moved rigidly bear on its contacts from the
        first step as it did before."""
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[self._qpos] = positions - self._body_origin
        if velocities is not None:
            self.data.qvel[self._dof] = velocities
        if warmstart is not None:
            self.data.qacc_warmstart[:] = warmstart
        mujoco.mj_forward(self.model, self.data)

    # ----- the settled-state library (services.sim.settled) -----
    def place_origin(self) -> None:
        self._set_vertices(self._flat_points)

    def act(self, action: ClothAction) -> None:
        self._carry(action)

    def physics_state(self) -> np.ndarray:
        """Positions, velocities and the solver's warm start: all the physics carries over."""
        return np.concatenate([self.data.qpos, self.data.qvel, self.data.qacc_warmstart])

    def load_physics_state(self, physics: np.ndarray) -> None:
        nq, nv = self.model.nq, self.model.nv
        if physics.shape != (nq + 2 * nv,):
            raise WorldError(f"a settled state of shape {physics.shape} does not fit this cloth")
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[:] = physics[:nq]
        self.data.qvel[:] = physics[nq : nq + nv]
        self.data.qacc_warmstart[:] = physics[nq + nv :]
        mujoco.mj_forward(self.model, self.data)

    def scene_hash(self) -> str:
        """sha256 of all that shapes a settled cloth: the physics MJCF, the motion recipe, the
        moves and MuJoCo's version (rendering options and the image size do not count)."""
        mjcf, recipe, shape = self._scene()
        document = {
            "mujoco": mujoco.__version__,
            "physics": "qpos qvel qacc_warmstart",
            "mjcf": mjcf,
            "recipe": {**recipe, "settle": [SETTLE_MIN_SECONDS, SETTLE_MAX_SECONDS, SETTLE_SPEED]},
            "moves": [[m.kind, m.fold, list(m.action)] for m in self.task.moves.values()],
            **shape,
        }
        return hashlib.sha256(json.dumps(document, sort_keys=True).encode()).hexdigest()

    # ----- reset, perturb, settle -----
    def reset(self, state: Folds, rng: np.random.Generator) -> Folds:
        """Load a settled cloth of `state` (one of its fold orders, drawn), put it down at a
        fresh pose within the reset noise and let it come to rest."""
        state = self.task.parse_state(self.task.state_to_json(state))
        orders = self.reset_orders(state)
        physics = self.library.variant(self, orders[int(rng.integers(len(orders)))])
        nq, nv = self.model.nq, self.model.nv
        positions = physics[:nq][self._qpos] + self._body_origin
        velocities = physics[nq : nq + nv][self._dof]
        moved = rigid(positions, rng, RESET_SHIFT, RESET_TURN, velocities)
        self._set_vertices(*moved, warmstart=physics[nq + nv :])
        self._settle(RESETTLE_MIN_SECONDS)
        return self.read_state()

    def reset_by_physics(self, state: Folds, rng: np.random.Generator) -> Folds:
        """The state reached by physics alone: the flat cloth at a fresh pose, folded in one of
        the state's orders (drawn) with a demonstrator's clicks (what `reset` stands in for)."""
        state = self.task.parse_state(self.task.state_to_json(state))
        orders = self.reset_orders(state)
        self._set_vertices(rigid(self._flat_points, rng, RESET_SHIFT, RESET_TURN)[0])
        for action in orders[int(rng.integers(len(orders)))]:
            self._carry(self.demonstrated(action, rng))
        return self.read_state()

    def perturb(self, rng: np.random.Generator) -> Folds:
        """The same state after a small rigid shift and turn of the whole cloth, settled.

        The new pose is drawn about the state's reference pose, not the current one, so that
        repeated perturbations never walk the cloth away from where the task's clicks expect it.
        """
        state = self.read_state()
        points = self.vertices()
        rotation, centroid, target = self.pose(points, state)
        points[:, :2] = (points[:, :2] - centroid) @ rotation + target  # the reference pose
        moved = rigid(points, rng, PERTURB_SHIFT, PERTURB_TURN)[0]
        self._set_vertices(moved, warmstart=self.data.qacc_warmstart.copy())
        self._settle(RESETTLE_MIN_SECONDS)
        after = self.read_state()
        if after != state:
            raise WorldError(f"the perturbed cloth reads as {after}, not {state}")
        return after

    def pose(self, points: np.ndarray, state: Folds) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rotation, centroid, target): (p - centroid) @ rotation + target puts the cloth on
        its state's reference, fitted on the vertices that agree with it."""
        reference = self._references[state]
        return fit(points[:, :2], reference, ~far(points[:, :2], reference))

    def demonstrated(self, action: ClothAction, rng: np.random.Generator) -> ClothAction:
        """`action` as a demonstrator would click it: a few pixels off, still the same move."""
        frame = self.task.frame
        noise = np.clip(rng.normal(0, CLICK_NOISE, 4), -2 * CLICK_NOISE, 2 * CLICK_NOISE)
        values = np.clip(np.rint(np.array([*action.pick, *action.release]) + noise), 0, frame - 1)
        v = values.astype(int).tolist()
        return ClothAction(Pixel(v[0], v[1]), Pixel(v[2], v[3]), action.height)

    def _settle(self, min_seconds: float = SETTLE_MIN_SECONDS) -> None:
        dt = self.model.opt.timestep
        for step in range(int(SETTLE_MAX_SECONDS / dt)):
            self._step()
            if step * dt > min_seconds and self._speed() < SETTLE_SPEED:
                break

    def _step(self) -> None:
        """One physics step; every 25 (0.1 s of cloth time) the request's deadline is checked,
        so that work nobody waits for any more stops between steps."""
        mujoco.mj_step(self.model, self.data)
        self._steps += 1
        if self._steps % 25 == 0:
            check_deadline()

    def _speed(self) -> float:
        return float(np.abs(self.data.qvel).max(initial=0.0))

    # ----- looking -----
    def read_state(self) -> Folds:
        if not np.isfinite(self.data.flexvert_xpos).all():
            raise WorldError("the cloth's vertices are not finite: the simulation diverged")
        shares = self.far_shares()
        best = min(shares, key=shares.__getitem__)
        if shares[best] >= self.max_far_share:
            raise WorldError(
                f"the cloth matches no state: nearest is {self.task.state_to_json(best)} with "
                f"{100 * shares[best]:.1f}% of {self.share_of} over {100 * FAR:g} cm off "
                f"(a match needs under {100 * self.max_far_share:g}%)"
            )
        return best

    max_far_share = 0.05  # a state matches when fewer vertices than this share are far
    share_of = "vertices"  # what the share counts, for messages

    def far_shares(self) -> dict[Folds, float]:
        """Share of vertices far from each state's reference: the read-back's evidence."""
        points = self.vertices()[:, :2]
        return {s: float(far(points, ref).mean()) for s, ref in self._references.items()}

    # ----- acting -----
    # Whether each move ends with the cloth smoothed to the settled shape of the state it reads
    # as (at a fresh pose within the reset noise), as a folding robot flattens the garment
    # between folds: the move's physics decides the state, the smoothing only its look. Without
    # it layered flaps drift over a walk of moves until a later move fails, and a state's images
    # differ by how it was reached (the T-shirt world).
    smooth_after_moves = False

    def execute(self, action: ClothAction, rng: np.random.Generator) -> Folds:
        self.task.check_action(self.read_state(), action)  # raises before anything moves
        try:
            self._carry(action)
        except InvalidActionError as exc:  # a legal move, but the cloth is not where it expects
            raise WorldError(f"the cloth has moved away from the move's pick: {exc}") from None
        state = self.read_state()
        if self.smooth_after_moves and self.reset(state, rng) != state:
            raise WorldError(f"the smoothed cloth no longer reads as {state}")
        return state

    def _timing(self, length: float, speed: float) -> np.ndarray:
        """Min-jerk progress (0..1] for each physics step of a move of `length` metres."""
        steps = max(2, int(np.ceil(length / speed / self.model.opt.timestep)))
        return np.array([min_jerk(k / steps) for k in range(1, steps + 1)])


def min_jerk(t: float) -> float:
    return t**3 * (10 - 15 * t + 6 * t**2)


def rigid(
    points: np.ndarray,
    rng: np.random.Generator,
    shift: float,
    turn: float,
    velocities: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray | None]:
    """`points` turned about their centroid and shifted in the table plane, uniformly at random,
    and `velocities` turned with them."""
    angle = rng.uniform(-turn, turn)
    c, s = np.cos(angle), np.sin(angle)
    rotation = np.array([[c, s], [-s, c]])
    centroid = points[:, :2].mean(axis=0)
    out = points.copy()
    out[:, :2] = (points[:, :2] - centroid) @ rotation + centroid
    out[:, :2] += rng.uniform(-shift, shift, size=2)
    if velocities is not None:
        velocities = velocities.copy()
        velocities[:, :2] = velocities[:, :2] @ rotation
    return out, velocities


def far(points: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Which vertices lie over FAR from `reference` after the best rigid 2-D alignment, fitted
    again on the vertices that agree (a folded flap must not pull the fit)."""
    keep = np.ones(len(points), bool)
    for _ in range(3):
        rotation, centroid, target = fit(points, reference, keep)
        out = np.linalg.norm((points - centroid) @ rotation + target - reference, axis=1) > FAR
        if (~out).sum() < 3 or np.array_equal(~out, keep):
            break
        keep = ~out
    return out


def fit(
    points: np.ndarray, reference: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Kabsch in 2-D: (rotation, centroid, target) with (points - centroid) @ rotation + target
    closest to `reference` over the `weights` rows."""
    p, q = points[weights], reference[weights]
    pc, qc = p.mean(axis=0), q.mean(axis=0)
    u, _, vt = np.linalg.svd((p - pc).T @ (q - qc))
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1, d]) @ vt, pc, qc
