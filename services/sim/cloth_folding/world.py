"""The cloth-folding world in MuJoCo physics: click pixels, grasp a vertex, turn the page.

A pick pixel becomes the cloth vertex under it (the lowest layer for height 0, the top layer for
height 1); a mocap gripper carries it along a half circle to the release pixel, lays it on
whatever lies there, lets go and lets the cloth settle. The state is read back by comparing the
vertices, after a rigid alignment, with each state's ideal folded cloth.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np

from services.sim.cloth_folding.scene import (
    PAD_SLOTS,
    TEXTURE_FILE,
    ClothGeometry,
    build_mjcf,
    cloth_texture,
    flat_mesh,
)
from services.sim.flex_world import FlexWorld
from services.sim.rendering import mujoco
from shared.tasks.base import InvalidActionError
from shared.tasks.cloth_folding import CORNER_DIRECTIONS, ClothAction, ClothFolding, Folds, Pixel

# The motion recipe. A plane table, elliptic friction cones, 0.6 m/s, a 0.1 s hold and a 0.15 s
# minimum settle fold 45% faster than the first recipe (a box table, pyramidal cones, 0.4 m/s,
# 0.15 s, 0.3 s) and land as close to the ideal cloth (60 noisy moves: mean vertex error 0.3 mm
# both, no failed move), with renders identical to a gray level.
CARRY_SPEED = 0.6  # m/s along the arc
ARC_HEIGHT = 0.95  # share of the arc's radius the grasped vertex rises
PLACE_CLEARANCE = 2.5  # radii above whatever lies under the release point
HOLD_SECONDS = 0.1


class ClothFoldingWorld(FlexWorld):
    def __init__(
        self,
        task: ClothFolding | None = None,
        image_size: int = 64,
        geometry: ClothGeometry | None = None,
        lattice: int | None = None,
        library: Sequence[Path] | None = None,
    ) -> None:
        """`lattice` (vertices along a side) overrides the geometry's: 5 makes a fast test cloth.
        `library`: the folders searched for this scene's settled states."""
        task = task or ClothFolding()
        self.geometry = geometry or ClothGeometry()
        if lattice is not None:
            self.geometry = replace(self.geometry, lattice=lattice)
        self.radius = self.geometry.radius
        xml = build_mjcf(task.config, self.geometry, image_size)
        flat, triangles = flat_mesh(self.geometry)
        assets = {TEXTURE_FILE: cloth_texture()}
        super().__init__(task, image_size, xml, assets, flat, triangles, library)
        self._pads = [self.model.equality(f"pad{i}").id for i in range(PAD_SLOTS)]

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

    def _scene(self) -> tuple[str, dict[str, Any], dict[str, Any]]:
        recipe = {
            "carry_speed": CARRY_SPEED,
            "arc_height": ARC_HEIGHT,
            "place_clearance": PLACE_CLEARANCE,
            "hold": HOLD_SECONDS,
        }
        mjcf = build_mjcf(self.task.config, self.geometry, 64)
        return mjcf, recipe, {"geometry": asdict(self.geometry)}

    def reset_orders(self, state: Folds) -> list[tuple[ClothAction, ...]]:
        """Every order of folding the state's corners: resets draw one, as a person would."""
        folds = [self.task.moves["fold", corner].action for corner in state]
        return list(itertools.permutations(folds))

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
        for s in self._timing(np.pi * radius, CARRY_SPEED):
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
