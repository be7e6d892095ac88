"""MJCF of the rope-box world: two boxes, a 1D flex rope between them and four pillars on a
checkered 3 x 3 grid, under a camera looking straight down (LSR-v2's scene).

The rope collides with the floor and the pillars but not with the boxes: its ends are tied
under the boxes' centres, so that the rope's path between them is all that tells its state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from shared.tasks.rope_box import BOXES, RopeBoxConfig

# contact bits: the floor and pillars touch everything, boxes touch boxes, the rope the rope
STATIC, BOX, ROPE = 7, 2, 4
BOX_RGB = {"green": "0.15 0.65 0.2", "orange": "0.95 0.5 0.1"}


@dataclass(frozen=True)
class RopeBoxGeometry:
    cell: float = 0.08  # metres between cell centres
    box_size: float = 0.036  # edge of a cube
    pillar_radius: float = 0.008
    pillar_height: float = 0.015
    rope_radius: float = 0.0055
    rope_vertices: int = 24
    rope_mass: float = 0.01
    noise: float = 0.006  # uniform in-cell noise of a box, +- metres
    fovy: float = 40.0
    view_cells: float = 3.7  # cells the canonical view spans (the grid and a margin)

    @property
    def half(self) -> float:
        return self.box_size / 2

    def camera_height(self) -> float:
        return self.view_cells * self.cell / 2 / math.tan(math.radians(self.fovy) / 2)

    def cell_xy(self, row: float, col: float, size: int) -> tuple[float, float]:
        """Table metres (x right, y up in the image) of a grid point in cell units."""
        middle = (size - 1) / 2
        return (col - middle) * self.cell, (middle - row) * self.cell


def box_body(box: str) -> str:
    return f"box_{box}"


def build_mjcf(config: RopeBoxConfig, geometry: RopeBoxGeometry, image_size: int) -> str:
    g, n = geometry, config.size
    pillars = []
    for i, p in enumerate(config.pillars):
        x, y = g.cell_xy(p.row + 0.5, p.col + 0.5, n)
        pillars.append(
            f'<geom name="pillar_{i}" type="cylinder" pos="{x:.4f} {y:.4f} {g.pillar_height / 2}" '
            f'size="{g.pillar_radius} {g.pillar_height / 2}" rgba="0.12 0.12 0.14 1" '
            f'contype="{STATIC}" conaffinity="{STATIC}"/>'
        )
    bodies, welds, ends = [], [], []
    for i, box in enumerate(BOXES):
        bodies.append(
            f'<body name="{box_body(box)}" pos="{0.6 + 0.1 * i} 0.6 {g.half}">'
            f'<freejoint/><geom type="box" size="{g.half} {g.half} {g.half}" '
            f'rgba="{BOX_RGB[box]} 1" mass="0.05" friction="0.6 0.005 0.0001" '
            f'contype="{BOX}" conaffinity="{BOX}"/></body>'
        )
        welds.append(
            f'<weld name="grip_{box}" body1="gripper" body2="{box_body(box)}" '
            'relpose="0 0 0 1 0 0 0" active="false" solref="0.02 1"/>'
        )
        # run time ties each end's vertex body (model.eq_obj2id) under its box's centre
        ends.append(
            f'<connect name="end_{box}" body1="{box_body(box)}" body2="world" '
            f'anchor="0 0 {g.rope_radius - g.half}" solref="0.01 1"/>'
        )
    length = config.rope_cells * g.cell
    points = " ".join(
        f"{(i / (g.rope_vertices - 1) - 0.5) * length:.5f} 0.5 0" for i in range(g.rope_vertices)
    )
    elements = " ".join(f"{i} {i + 1}" for i in range(g.rope_vertices - 1))
    grid = n * g.cell
    return f"""
<mujoco model="rope_box">
  <compiler angle="radian"/>
  <option timestep="0.002" integrator="implicitfast" solver="Newton" jacobian="sparse"
          cone="elliptic"/>
  <visual>
    <global offwidth="{image_size}" offheight="{image_size}"/>
    <quality shadowsize="0"/>
    <headlight ambient="0.5 0.5 0.5" diffuse="0.4 0.4 0.4" specular="0 0 0"/>
  </visual>
  <asset>
    <texture name="tex_grid" type="2d" builtin="checker" width="64" height="64"
             rgb1="0.72 0.72 0.74" rgb2="0.56 0.57 0.60"/>
    <material name="mat_grid" texture="tex_grid" texrepeat="{n / 2} {n / 2}" reflectance="0"/>
    <texture name="tex_table" type="2d" builtin="flat" width="8" height="8" rgb1="0.66 0.62 0.56"/>
    <material name="mat_table" texture="tex_table" reflectance="0"/>
  </asset>
  <worldbody>
    <light name="sun" directional="true" pos="0 0 1" dir="0.2 0.3 -1" castshadow="false"
           diffuse="0.4 0.4 0.4"/>
    <geom name="table" type="box" pos="0 0 -0.02" size="2 2 0.02" material="mat_table"
          friction="0.6" contype="{STATIC}" conaffinity="{STATIC}"/>
    <geom name="grid" type="box" pos="0 0 0.0002" size="{grid / 2} {grid / 2} 0.0002"
          material="mat_grid" contype="0" conaffinity="0"/>
    {"".join(pillars)}
    <camera name="top" pos="0 0 {g.camera_height():.5f}" xyaxes="1 0 0 0 1 0" fovy="{g.fovy}"/>
    <body name="gripper" mocap="true" pos="0.5 -0.5 0.3"/>
    {"".join(bodies)}
    <flexcomp name="rope" type="direct" dim="1" dof="full" radius="{g.rope_radius}"
              mass="{g.rope_mass}" rgba="0.8 0.1 0.1 1" pos="0 0 {g.rope_radius}"
              point="{points}" element="{elements}">
      <edge equality="true" solref="0.004 1" damping="0.002"/>
      <contact condim="3" friction="0.4" contype="{ROPE}" conaffinity="{ROPE}"
               selfcollide="none"/>
    </flexcomp>
  </worldbody>
  <equality>
    {"".join(welds)}
    {"".join(ends)}
    <connect name="hand" body1="gripper" body2="world" anchor="0 0 0" active="false"
             solref="0.01 1"/>
  </equality>
</mujoco>
"""
