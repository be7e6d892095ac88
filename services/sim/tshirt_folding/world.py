"""The T-shirt world in MuJoCo physics: a flap turned over its fold line as a plate.

A move's pick and release name the move (within the task's tolerance); the hand folds on the
garment's own fold line where the shirt lies now, as a folding cell that sees the garment does,
so that any click naming the move makes it (benchmarks/bench_landing.py). The gripper takes
the cloth on the flap's side of that line near the pick: every layer there (height 0) or the
folded flap lying on top (height 1), as a folding board takes a flap, and turns it about the
line onto its mirror image, lays it down, lets go and lets the shirt settle. The state is read
back part by part (sleeves, side strips, middle; top and bottom halves), so that a sleeve
hidden in its side flap counts.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from services.sim.flex_world import (
    FlexWorld,
    far,
)
from services.sim.tshirt_folding.scene import (
    TEXTURE_FILE,
    ShirtMesh,
    build_mjcf,
    flat_mesh,
    shirt_texture,
)
from shared.tasks.base import InvalidActionError
from shared.tasks.folding import ClothAction, Folds
from shared.tasks.tshirt_folding import FOLDS, TshirtFolding

TURN_SPEED = 0.3  # m/s of the flap's far edge along its half circle
PLACE_CLEARANCE = 2.5  # radii between the turned flap and whatever lies under it
HOLD_SECONDS = 0.1
LANDING_SLOPE = 0.25  # m a metre: how steeply a turned flap's landing heights may change
CREASE_BAND = 0.008  # m: vertices this close to the fold line belong to neither side
# A state matches when every part has fewer far vertices than this share. Measured over 156
# right noisy moves (benchmarks/bench_transitions.py): at most 13.2% in the state's own parts,
# at least 50% in some part of any other state.
MAX_PART_FAR = 0.25
PARTS = ("left_sleeve", "right_sleeve", "left_strip", "right_strip", "middle")


class TshirtFoldingWorld(FlexWorld):
    max_far_share = MAX_PART_FAR
    share_of = "some part's vertices"
    # Walks of moves without it: 3 of 12 moves failed in one data-generation episode (a fold
    # from a state reached by two unfolds 75% off), against 1 in 160 moves from settled states.
    smooth_after_moves = True

    def __init__(
        self,
        task: TshirtFolding | None = None,
        image_size: int = 64,
        mesh: ShirtMesh | None = None,
        library: Sequence[Path] | None = None,
    ) -> None:
        task = task or TshirtFolding()
        self.mesh = mesh or ShirtMesh()
        self.radius = self.mesh.radius
        flat, triangles = flat_mesh(task.config, self.mesh)
        self._rest = flat
        self._slots = len(flat)  # a hand for every vertex: the flap and the base held
        xml = build_mjcf(task.config, self.mesh, image_size, self._slots)
        assets = {TEXTURE_FILE: shirt_texture(task.config)}
        self._parts = self._part_masks(task, flat)
        super().__init__(task, image_size, xml, assets, flat, triangles, library)
        self._grips = np.array([self.model.equality(f"grip{i}").id for i in range(self._slots)])
        self.spacing = task.config.body_width / self.mesh.body_columns  # lattice, metres

    # ----- the garment's parts, by rest coordinates -----
    @staticmethod
    def _part_masks(task: TshirtFolding, rest: np.ndarray) -> list[np.ndarray]:
        c = task.config
        x, y = rest[:, 0], rest[:, 1]
        eps = 1e-9
        columns = {
            "left_sleeve": x < -c.armhole - eps,
            "right_sleeve": x > c.armhole + eps,
            "left_strip": (x >= -c.armhole - eps) & (x < -c.side_line - eps),
            "right_strip": (x <= c.armhole + eps) & (x > c.side_line + eps),
            "middle": np.abs(x) <= c.side_line + eps,
        }
        masks = []
        for name in PARTS:
            for half in (y >= -eps, y < -eps):
                mask = columns[name] & half
                if mask.any():
                    masks.append(mask)
        return masks

    def _flap(self, fold: str, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(flap, crease) masks of `fold` by rest coordinates."""
        point, normal = self.task.fold_line(fold)
        beyond = (self._rest - point) @ normal
        return beyond > 1e-9, np.abs(beyond) <= 1e-9

    def _reference(self, state: Folds) -> np.ndarray:
        """(V, 2) vertex positions of the ideal shirt in `state`: each fold, in the only order
        the rules allow (sleeves, sides, bottom half), mirrors its flap over its fold line."""
        points = self._rest.copy()
        for fold in FOLDS:
            if fold in state:
                point, normal = self.task.fold_line(fold)
                flap, _ = self._flap(fold, points)
                beyond = (points[flap] - point) @ normal
                points[flap] -= 2 * beyond[:, None] * normal
        return points

    def far_shares(self) -> dict[Folds, float]:
        """For each state, the largest share of far vertices in any part of the shirt."""
        points = self.vertices()[:, :2]
        shares = {}
        for state, reference in self._references.items():
            out = far(points, reference)
            shares[state] = max(float(out[mask].mean()) for mask in self._parts)
        return shares

    # ----- the settled-state library -----
    def _scene(self) -> tuple[str, dict[str, Any], dict[str, Any]]:
        recipe = {
            "turn_speed": TURN_SPEED,
            "place_clearance": PLACE_CLEARANCE,
            "hold": HOLD_SECONDS,
            "crease_band": CREASE_BAND,
            "landing_slope": LANDING_SLOPE,
        }
        mjcf = build_mjcf(self.task.config, self.mesh, 64, self._slots)
        return mjcf, recipe, {"mesh": asdict(self.mesh)}

    def reset_orders(self, state: Folds) -> list[tuple[ClothAction, ...]]:
        """Every order of folding the state's folds that the rules allow: resets draw one."""
        moves = self.task.moves
        orders: list[tuple[ClothAction, ...]] = []

        def extend(done: Folds, order: tuple[ClothAction, ...]) -> None:
            if len(done) == len(state):
                orders.append(order)
                return
            for fold in state:
                move = moves["fold", fold]
                if fold not in done and self.task.refusal(done, move) is None:
                    after = tuple(f for f in FOLDS if f in done or f == fold)
                    extend(after, (*order, move.action))

        extend((), ())
        return orders

    # ----- acting -----
    def grasp(self, action: ClothAction) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(grasped vertex indices, a point on the fold line, the unit normal towards the
        flap) in table coordinates; InvalidActionError when the pick finds no cloth to take.

        The click names the move (within the task's tolerance); the hand folds on the
        garment's own fold line where the shirt lies now, towards the move's flap (a fold's
        beyond the line, an unfold's folded back over it), as a folding cell that sees the
        garment does. The pick says where to take the cloth: what lies within the hand's reach
        of it, or else the nearest cloth of the flap within the tolerance, so that any click
        naming the move makes it (benchmarks/bench_landing.py)."""
        move = self.task.match(action)
        if move is None:
            raise InvalidActionError(f"action: {tuple(action)} names no move of the T-shirt")
        points = self.vertices()
        rotation, centroid, target = self.pose(points, self.read_state())
        point, normal = self.task.fold_line(move.fold)
        line = (point - target) @ rotation.T + centroid  # the garment's line as it lies now
        normal = normal @ rotation.T * (1.0 if move.kind == "fold" else -1.0)
        side = (points[:, :2] - line) @ normal
        flap, crease = self._flap(move.fold, points)
        takeable = (side > CREASE_BAND) & ~crease
        # height 1 (an unfold) takes the folded flap lying on top, not the cloth it lies on
        graspable = takeable & flap if action.height == 1 else takeable
        centre = np.array([action.pick.col + 0.5, action.pick.row + 0.5])
        distance = np.where(
            graspable, np.linalg.norm(self.to_pixels(points) - centre, axis=1), np.inf
        )
        reach = 0.75 * self.spacing * self._focal / self._camera_height
        near = np.flatnonzero(distance <= reach)
        if len(near) == 0 and distance.min() <= reach + self.task.tolerance:
            near = np.array([int(np.argmin(distance))])
        if len(near) == 0:
            where = f"of the folded {move.fold}" if action.height == 1 else "on the flap's side"
            raise InvalidActionError(
                f"action.pick: pixel {tuple(action.pick)} hits no cloth {where} (no vertex "
                f"within {reach + self.task.tolerance:.1f} px)"
            )
        seeds = [int(near[np.argmin(distance[near])])] if action.height == 1 else near.tolist()
        taken = self._component(seeds, takeable)
        return np.flatnonzero(taken), line, normal

    def _component(self, seeds: list[int], allowed: np.ndarray) -> np.ndarray:
        """The mesh-connected pieces of `allowed` vertices that hold a seed."""
        taken = np.zeros(len(allowed), bool)
        taken[seeds] = True
        queue = deque(seeds)
        while queue:
            for other in self._ring[queue.popleft()]:
                if allowed[other] and not taken[other]:
                    taken[other] = True
                    queue.append(other)
        return taken

    def _carry(self, action: ClothAction) -> None:
        """Take the flap, turn it over the fold line onto whatever lies there, lay it down, let
        go, settle; meanwhile a second hand holds the rest of the cloth along the fold line.

        Each taken vertex turns about the fold line on its own half circle, whose height is
        chosen so that it lands just above what lies under its mirror image, keeping the
        flap's own layers in their (turned over) order: a rigid plate would land at the height
        of the thickest spot and leave thick folds hanging in the air, strained at the crease.
        """
        taken, middle, normal = self.grasp(action)
        points = self.vertices()
        side = (points[:, :2] - middle) @ normal
        others = np.ones(len(points), bool)
        others[taken] = False
        lying_on = _within(points[:, :2], points[taken, :2], 0.75 * self.spacing) & (
            points[:, 2, None] > points[taken, 2][None] + self.radius
        )
        near_line = (np.abs(side) > CREASE_BAND) & (np.abs(side) < self.spacing)
        crease = self._flap(self.task.match(action).fold, points)[1]  # free to bend
        held = np.flatnonzero(others & near_line & ~crease & ~lying_on.any(axis=1))
        if len(taken) + len(held) > self._slots:
            raise InvalidActionError(f"action: the flap has {len(taken)} vertices, over a hand")
        start = points[taken]
        mirrored = start[:, :2] - 2 * side[taken, None] * normal
        below = _within(mirrored, points[others, :2], self.spacing)
        ground = np.where(below, points[others, 2][None], -self.radius).max(axis=1)
        above = _within(start[:, :2], start[:, :2], 0.75 * self.spacing)
        stack_top = np.where(above, start[:, 2][None], -np.inf).max(axis=1)
        # Where the flap lands over thicker and thinner spots, the landing heights rise and fall
        # at most LANDING_SLOPE: a step between neighbours would be stretched edges, and they
        # spring up when the hand lets go.
        floor = ground + PLACE_CLEARANCE * self.radius
        apart = np.linalg.norm(mirrored[:, None] - mirrored[None], axis=2)
        floor = (floor[None] - LANDING_SLOPE * apart).max(axis=1)
        landing = floor + (stack_top - start[:, 2])
        pivot = (start[:, 2] + landing) / 2  # per vertex: z lands at 2 pivot - z
        turn_n, z = np.array([*normal, 0.0]), np.array([0.0, 0.0, 1.0])
        out = side[taken][:, None]  # distance out from the fold line
        rise = (start[:, 2] - pivot)[:, None]  # height above the vertex's own fold axis
        centre = start - out * turn_n - rise * z  # each vertex's point on its own fold axis
        reach = float(np.hypot(side[taken], start[:, 2] - pivot).max())

        grip = self.data.mocap_pos[self._grip] = np.zeros(3)
        self.data.mocap_quat[self._grip] = (1, 0, 0, 0)
        slots = self._grips[: len(taken) + len(held)]
        moving, holding = slots[: len(taken)], slots[len(taken) :]
        self.model.eq_obj2id[slots] = self._vertex_body[np.concatenate([taken, held])]
        self.model.eq_data[slots, :6] = 0.0
        self.model.eq_data[moving, :3] = start - grip
        self.model.eq_data[holding, :3] = points[held] - grip
        self.data.eq_active[slots] = 1
        for s in self._timing(np.pi * reach, TURN_SPEED):
            c, n = np.cos(np.pi * s), np.sin(np.pi * s)
            # the part along +normal turns up, then over; the part along +z turns to -normal
            targets = centre + out * (c * turn_n + n * z) + rise * (c * z - n * turn_n)
            self.model.eq_data[moving, :3] = targets - grip
            self._step()
        for _ in range(int(HOLD_SECONDS / self.model.opt.timestep)):
            self._step()
        self.data.eq_active[slots] = 0
        self._settle()


def _within(a: np.ndarray, b: np.ndarray, distance: float) -> np.ndarray:
    """(len(a), len(b)): which points of b lie within `distance` of each point of a."""
    return np.linalg.norm(a[:, None] - b[None], axis=2) < distance
