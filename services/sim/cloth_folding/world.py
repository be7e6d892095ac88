"""The cloth-folding world in MuJoCo physics: click pixels, grasp a vertex, turn the page.

A pick pixel becomes the cloth vertex under it (the lowest layer for height 0, the top layer for
height 1); a mocap gripper carries it along a half circle to the release pixel, lays it on
whatever lies there, lets go and lets the cloth settle. The state is read back by comparing the
vertices, after a rigid alignment, with each state's ideal folded cloth.
"""

from __future__ import annotations

import hashlib
import itertools
import json
from collections.abc import Sequence
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from services.sim.cloth_folding.scene import (
    PAD_SLOTS,
    TEXTURE_FILE,
    ClothGeometry,
    build_mjcf,
    cloth_texture,
    flat_mesh,
)
from services.sim.rendering import OffscreenCamera, mujoco
from services.sim.settled import SettledLibrary
from shared.deadlines import check_deadline
from shared.tasks.base import InvalidActionError, World, WorldError
from shared.tasks.cloth_folding import (
    CORNER_DIRECTIONS,
    ClothAction,
    ClothFolding,
    Folds,
    Pixel,
)

# The motion recipe. A plane table, elliptic friction cones, 0.6 m/s, a 0.1 s hold and a 0.15 s
# minimum settle fold 45% faster than the first recipe (a box table, pyramidal cones, 0.4 m/s,
# 0.15 s, 0.3 s) and land as close to the ideal cloth (60 noisy moves: mean vertex error 0.3 mm
# both, no failed move), with renders identical to a gray level.
CARRY_SPEED = 0.6  # m/s along the arc
ARC_HEIGHT = 0.95  # share of the arc's radius the grasped vertex rises
PLACE_CLEARANCE = 2.5  # radii above whatever lies under the release point
HOLD_SECONDS = 0.1
SETTLE_MAX_SECONDS = 1.2
SETTLE_MIN_SECONDS = 0.15
SETTLE_SPEED = 0.02  # m/s: the cloth counts as at rest below this
# A settled cloth moved rigidly (its warm start kept) is at rest at once: under 0.3 mm in 20
# steps, so two steps show it. Walks of data generation whose move wrecked the cloth (about 1%,
# a top-layer pick where three flap tips meet): 2 of 230 with two steps, 1 of 170 with 12.
RESETTLE_MIN_SECONDS = 0.0
FAR = 0.03  # m: a vertex this far from a state's reference cloth does not match it
MAX_FAR_SHARE = 0.05  # a state matches when fewer vertices than this share are far
CLICK_NOISE = 1.5  # pixels (standard deviation, clipped at 2x) of a demonstrator's clicks
RESET_SHIFT = 0.003  # m, uniform, of the flat cloth that reset() starts from
RESET_TURN = np.deg2rad(1.0)
PERTURB_SHIFT = 0.005  # m, uniform: the no-action perturbation (paper: "slightly perturbing")
PERTURB_TURN = np.deg2rad(2.0)


class ClothFoldingWorld(World[Folds, ClothAction]):
    episode_length = 10  # tuples walked from a reset: folded states come from physics
    settles = True

    def __init__(
        self,
        task: ClothFolding | None = None,
        image_size: int = 64,
        geometry: ClothGeometry | None = None,
        lattice: int | None = None,
        library: Sequence[Path] | None = None,
    ) -> None:
        """`lattice` (vertices along a side) overrides the geometry's: 5 makes a fast test cloth.
        `library`: the folders searched for this scene's settled states (default: the shipped
        models', then the cache); without one, each state is folded once, on first use."""
        self.task = task or ClothFolding()
        self.image_size = image_size
        self.geometry = geometry or ClothGeometry()
        if lattice is not None:
            self.geometry = replace(self.geometry, lattice=lattice)
        xml = build_mjcf(self.task.config, self.geometry, image_size)
        self.model = mujoco.MjModel.from_xml_string(xml, {TEXTURE_FILE: cloth_texture()})
        self.data = mujoco.MjData(self.model)
        self.camera = OffscreenCamera(self.model, "top", image_size)
        flex = 0
        first = int(self.model.flex_vertadr[flex])
        count = int(self.model.flex_vertnum[flex])
        self._vertex_body = self.model.flex_vertbodyid[first : first + count].copy()
        self._flat, triangles = flat_mesh(self.geometry)
        self._ring: list[set[int]] = [set() for _ in self._flat]
        for triangle in triangles.tolist():
            for v in triangle:
                self._ring[v].update(triangle)
        self._body_origin = self.model.body_pos[self._vertex_body].copy()
        dof = self.model.body_dofadr[self._vertex_body]
        xyz = np.arange(3)  # 3 slides a vertex
        self._qpos = self.model.jnt_qposadr[self.model.dof_jntid[dof]][:, None] + xyz
        self._dof = dof[:, None] + xyz
        lying = np.full(len(self._flat), self.geometry.radius)  # the flat cloth lies at z = radius
        self._flat_points = np.column_stack([self._flat, lying])
        self._grip = int(self.model.body("gripper").mocapid[0])
        self._pads = [self.model.equality(f"pad{i}").id for i in range(PAD_SLOTS)]
        self._references = {s: self._reference(s) for s in self.task.all_states()}
        cam = self.model.camera("top")
        self._camera_height = float(self.model.cam_pos[cam.id][2])
        self._focal = self.task.config.frame / 2 / np.tan(np.deg2rad(self.geometry.fovy) / 2)
        self.library = SettledLibrary.find(self.task, self.scene_hash(), library)
        self._steps = 0  # physics steps taken, for the deadline checks

    # ----- frames: metres on the table <-> pixels of the task's action frame -----
    def to_pixels(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) world points -> (N, 2) continuous (col, row) in the action frame."""
        points = np.atleast_2d(points)
        depth = self._camera_height - points[:, 2]
        half = self.task.config.frame / 2
        return np.stack(
            [half + self._focal * points[:, 0] / depth, half - self._focal * points[:, 1] / depth],
            axis=1,
        )

    def to_table(self, pixel: Pixel, z: float = 0.0) -> np.ndarray:
        """The point at height z seen at the centre of `pixel`."""
        half = self.task.config.frame / 2
        depth = self._camera_height - z
        x = (pixel.col + 0.5 - half) * depth / self._focal
        y = -(pixel.row + 0.5 - half) * depth / self._focal
        return np.array([x, y, z])

    def action_pixels(self, action: ClothAction) -> tuple[tuple[float, float], tuple[float, float]]:
        """Pick and release in this world's image: the action frame scaled to the image size."""
        scale = self.image_size / self.task.config.frame
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

    def _reference(self, state: Folds) -> np.ndarray:
        """(V, 2) vertex positions of the ideal cloth in `state`: flaps mirrored over the centre
        side of their fold lines (x dx + y dy = side / 2 for the corner's direction)."""
        points = self._flat.copy()
        half = self.geometry.side / 2
        for corner in state:
            dx, drow = CORNER_DIRECTIONS[corner]
            normal = np.array([dx, -drow]) / np.sqrt(2)  # image rows run down, y runs up
            offset = half / np.sqrt(2)
            beyond = points @ normal - offset
            flap = beyond > 1e-9
            points[flap] -= 2 * beyond[flap, None] * normal
        return points

    # ----- the settled-state library (services.sim.settled) -----
    def scene_hash(self) -> str:
        """sha256 of all that shapes a settled cloth: the physics MJCF, the motion recipe, the
        moves and MuJoCo's version (rendering options and the image size do not count)."""
        recipe = {
            "carry_speed": CARRY_SPEED,
            "arc_height": ARC_HEIGHT,
            "place_clearance": PLACE_CLEARANCE,
            "hold": HOLD_SECONDS,
            "settle": [SETTLE_MIN_SECONDS, SETTLE_MAX_SECONDS, SETTLE_SPEED],
        }
        document = {
            "mujoco": mujoco.__version__,
            "physics": "qpos qvel qacc_warmstart",
            "mjcf": build_mjcf(self.task.config, self.geometry, 64),
            "geometry": asdict(self.geometry),
            "recipe": recipe,
            "moves": [[m.kind, m.corner, list(m.action)] for m in self.task.moves.values()],
        }
        return hashlib.sha256(json.dumps(document, sort_keys=True).encode()).hexdigest()

    def reset_orders(self, state: Folds) -> list[tuple[ClothAction, ...]]:
        """Every order of folding the state's corners: resets draw one, as a person would."""
        folds = [self.task.moves["fold", corner].action for corner in state]
        return list(itertools.permutations(folds))

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
        moved = _rigid(positions, rng, RESET_SHIFT, RESET_TURN, velocities)
        self._set_vertices(*moved, warmstart=physics[nq + nv :])
        self._settle(RESETTLE_MIN_SECONDS)
        return self.read_state()

    def reset_by_physics(self, state: Folds, rng: np.random.Generator) -> Folds:
        """The state reached by physics alone: the flat cloth at a fresh pose, its corners
        folded in a random order with a demonstrator's clicks (what `reset` stands in for)."""
        state = self.task.parse_state(self.task.state_to_json(state))
        self._set_vertices(_rigid(self._flat_points, rng, RESET_SHIFT, RESET_TURN)[0])
        for corner in rng.permutation(np.array(state, dtype=object)).tolist():
            self._carry(self.demonstrated(self.task.moves["fold", corner].action, rng))
        return self.read_state()

    def perturb(self, rng: np.random.Generator) -> Folds:
        """The same state after a small rigid shift and turn of the whole cloth, settled.

        The new pose is drawn about the state's reference pose, not the current one, so that
        repeated perturbations never walk the cloth away from where the task's clicks expect it.
        """
        state = self.read_state()
        points = self.vertices()
        reference = self._references[state]
        rotation, centroid, target = _fit(points[:, :2], reference, self._agreeing(points, state))
        points[:, :2] = (points[:, :2] - centroid) @ rotation + target  # the reference pose
        moved = _rigid(points, rng, PERTURB_SHIFT, PERTURB_TURN)[0]
        self._set_vertices(moved, warmstart=self.data.qacc_warmstart.copy())
        self._settle(RESETTLE_MIN_SECONDS)
        after = self.read_state()
        if after != state:
            raise WorldError(f"the perturbed cloth reads as {after}, not {state}")
        return after

    def _agreeing(self, points: np.ndarray, state: Folds) -> np.ndarray:
        return ~_far(points[:, :2], self._references[state])

    def demonstrated(self, action: ClothAction, rng: np.random.Generator) -> ClothAction:
        """`action` as a demonstrator would click it: a few pixels off, still the same move."""
        frame = self.task.config.frame
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
    def render(self) -> np.ndarray:
        return self.camera.render(self.data)

    def read_state(self) -> Folds:
        if not np.isfinite(self.data.flexvert_xpos).all():
            raise WorldError("the cloth's vertices are not finite: the simulation diverged")
        shares = self.far_shares()
        best = min(shares, key=shares.__getitem__)
        if shares[best] >= MAX_FAR_SHARE:
            raise WorldError(
                f"the cloth matches no state: nearest is {self.task.state_to_json(best)} with "
                f"{100 * shares[best]:.1f}% of vertices over {100 * FAR:g} cm off "
                f"(a match needs under {100 * MAX_FAR_SHARE:g}%)"
            )
        return best

    def far_shares(self) -> dict[Folds, float]:
        """Share of vertices far from each state's reference: the read-back's evidence."""
        points = self.vertices()[:, :2]
        return {s: float(_far(points, ref).mean()) for s, ref in self._references.items()}

    # ----- acting -----
    def execute(self, action: ClothAction, rng: np.random.Generator) -> Folds:
        state = self.read_state()
        self.task.check_action(state, action)  # raises before anything moves
        try:
            self._carry(action)
        except InvalidActionError as exc:  # a legal move, but the cloth is not where it expects
            raise WorldError(f"the cloth has moved away from the move's pick: {exc}") from None
        return self.read_state()

    def grasp_vertex(self, pick: Pixel, height: int) -> int:
        """The vertex under `pick`: of the lowest layer there (height 0) or the top one (1)."""
        if height not in (0, 1):
            raise InvalidActionError(f"action.height: expected 0 or 1, got {height!r}")
        points = self.vertices()
        centre = np.array([pick.col + 0.5, pick.row + 0.5])
        distance = np.linalg.norm(self.to_pixels(points) - centre, axis=1)
        reach = 0.75 * self.geometry.spacing * self._focal / self._camera_height
        near = np.flatnonzero(distance <= reach)
        if len(near) == 0:
            raise InvalidActionError(
                f"action.pick: pixel {tuple(pick)} hits no cloth (no vertex within {reach:.1f} px)"
            )
        # Height 0: the bottom layer; height 1: a layer lying on another one.
        z = points[near, 2]
        upper = z > z.min() + 1.5 * self.geometry.radius
        keep = near[upper] if height == 1 else near[~upper]
        if len(keep) == 0:
            raise InvalidActionError(
                f"action.height: pixel {tuple(pick)} shows a single layer, there is no top layer"
            )
        return int(keep[np.argmin(distance[keep])])

    def _carry(self, action: ClothAction) -> None:
        """Pinch, turn the page along a half circle, lay down, hold, release, settle.

        The gripper's pad holds the grasped vertex and its mesh neighbours as one rigid patch
        and turns it over about the fold axis on the way, as a hand turns a page: the flap
        lands flat, its free end held rather than dangling and curling under.
        """
        vertex = self.grasp_vertex(action.pick, action.height)
        points = self.vertices()
        start = points[vertex]
        target = self.to_table(action.release)
        below = np.linalg.norm(points[:, :2] - target[:2], axis=1) < self.geometry.spacing
        below[sorted(self._ring[vertex])] = False
        ground = points[below, 2].max() if below.any() else self.geometry.radius
        target[2] = ground + PLACE_CLEARANCE * self.geometry.radius
        centre = (start[:2] + target[:2]) / 2
        radius = float(np.linalg.norm(target[:2] - start[:2])) / 2
        outward = np.array([*(start[:2] - centre), 0.0]) / max(radius, 1e-9)
        axis = np.cross(outward, [0.0, 0.0, 1.0])  # turns `outward` up, then over

        self.data.mocap_pos[self._grip] = start
        self.data.mocap_quat[self._grip] = (1, 0, 0, 0)
        pad = sorted(self._ring[vertex])  # at most 9: a lattice vertex and its 8 neighbours
        for slot, held in zip(self._pads[: len(pad)], pad, strict=True):
            self.model.eq_obj2id[slot] = self._vertex_body[held]
            self.model.eq_data[slot, :6] = 0.0
            self.model.eq_data[slot, :3] = points[held] - start  # pad offset, gripper frame
            self.data.eq_active[slot] = 1
        quat = np.zeros(4)
        for s in self._timing(np.pi * radius):
            angle = np.pi * s
            xy = centre + np.cos(angle) * (start[:2] - centre)
            z = start[2] + s * (target[2] - start[2]) + ARC_HEIGHT * radius * np.sin(angle)
            mujoco.mju_axisAngle2Quat(quat, axis, angle)
            self.data.mocap_quat[self._grip] = quat
            self.data.mocap_pos[self._grip] = (*xy, z)
            self._step()
        for _ in range(int(HOLD_SECONDS / self.model.opt.timestep)):
            self._step()
        self.data.eq_active[self._pads] = 0
        self._settle()

    def _timing(self, length: float) -> np.ndarray:
        """Min-jerk progress (0..1] for each physics step of a move of `length` metres."""
        steps = max(2, int(np.ceil(length / CARRY_SPEED / self.model.opt.timestep)))
        return np.array([_min_jerk(k / steps) for k in range(1, steps + 1)])

    def close(self) -> None:
        self.camera.close()


def _min_jerk(t: float) -> float:
    return t**3 * (10 - 15 * t + 6 * t**2)


def _rigid(
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


def _far(points: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Which vertices lie over FAR from `reference` after the best rigid 2-D alignment, fitted
    again on the vertices that agree (a folded flap must not pull the fit)."""
    keep = np.ones(len(points), bool)
    for _ in range(3):
        rotation, centroid, target = _fit(points, reference, keep)
        far = np.linalg.norm((points - centroid) @ rotation + target - reference, axis=1) > FAR
        if (~far).sum() < 3 or np.array_equal(~far, keep):
            break
        keep = ~far
    return far


def _fit(
    points: np.ndarray, reference: np.ndarray, weights: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Kabsch in 2-D: (rotation, centroid, target) with (points - centroid) @ rotation + target
    closest to `reference` over the `weights` rows."""
    p, q = points[weights], reference[weights]
    pc, qc = p.mean(axis=0), q.mean(axis=0)
    u, _, vt = np.linalg.svd((p - pc).T @ (q - qc))
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1, d]) @ vt, pc, qc
