"""MJCF of the box-stacking world, built from the task config: geometry lives in one place."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

from shared.tasks.box_stacking import BoxStackingConfig


@dataclass(frozen=True)
class SceneGeometry:
    box_size: float = 0.06  # edge of a cube, metres; one grid cell is one box
    column_spacing: float = 0.11  # distance between column centres along x
    noise_fraction: float = 0.17  # uniform in-cell noise, +- this fraction of the cell size

    @property
    def half(self) -> float:
        return self.box_size / 2

    @property
    def noise(self) -> float:
        return self.noise_fraction * self.box_size

    def column_x(self, col: int, columns: int) -> float:
        return (col - (columns - 1) / 2) * self.column_spacing

    def level_z(self, row: int) -> float:
        """Height of a box centre standing at level `row`."""
        return row * self.box_size + self.half


# Each box: MuJoCo texture attributes, a colour and a mark, so that boxes stay distinct in
# texture as well as hue. rgb2 colours the side faces of a "flat" cube texture, so it repeats
# rgb1. A world takes others (a scene with a box it was never trained on, for one).
BOX_LOOKS: Mapping[str, str] = {
    "red": 'builtin="flat" rgb1=".85 .12 .1" rgb2=".85 .12 .1" mark="edge" markrgb="1 1 1"',
    "green": 'builtin="checker" rgb1=".1 .65 .2" rgb2=".02 .3 .06"',
    "blue": 'builtin="flat" rgb1=".12 .25 .85" rgb2=".12 .25 .85" mark="cross" markrgb="1 1 1"',
    "yellow": (
        'builtin="flat" rgb1=".95 .8 .1" rgb2=".95 .8 .1" mark="random" random="0.08" '
        'markrgb=".2 .2 .2"'
    ),
}


def box_body(box: str) -> str:
    return f"box_{box}"


def grip_weld(box: str) -> str:
    return f"grip_{box}"


def build_mjcf(
    config: BoxStackingConfig,
    geometry: SceneGeometry,
    image_size: int,
    looks: Mapping[str, str] = BOX_LOOKS,
) -> str:
    g = geometry
    unknown = [b for b in config.boxes if b not in looks]
    if unknown:
        raise ValueError(f"no look defined for boxes {unknown}")
    assets, pads, bodies, welds = [], [], [], []
    for box in config.boxes:
        assets.append(
            f'<texture name="tex_{box}" type="cube" width="64" height="64" {looks[box]}/>'
            f'<material name="mat_{box}" texture="tex_{box}" specular="0.1" shininess="0.1"/>'
        )
    for col in range(config.columns):
        x = g.column_x(col, config.columns)
        pads.append(
            f'<geom name="pad_{col}" type="box" pos="{x} 0 0.0005" '
            f'size="{g.half * 1.6} {g.half * 1.6} 0.0005" rgba="0.55 0.55 0.58 1" '
            'contype="0" conaffinity="0"/>'
        )
    # Boxes start far apart; reset() places them.
    for i, box in enumerate(config.boxes):
        bodies.append(
            f'<body name="{box_body(box)}" pos="{0.6 + 0.1 * i} 0.6 {g.half}">'
            f'<freejoint name="joint_{box}"/>'
            f'<geom name="geom_{box}" type="box" size="{g.half} {g.half} {g.half}" '
            f'material="mat_{box}" mass="0.1" friction="1 0.005 0.0001"/>'
            "</body>"
        )
        welds.append(
            f'<weld name="{grip_weld(box)}" body1="gripper" body2="{box_body(box)}" '
            'relpose="0 0 0 1 0 0 0" active="false" solref="0.02 1"/>'
        )
    # Camera in front of the grid, looking down at its centre: column 0 appears on the left.
    span = g.column_spacing * (config.columns - 1) + 2 * g.box_size
    distance = 1.5 * span
    look_z = g.box_size * config.levels / 2
    elevation = 0.5  # radians above the horizontal
    cam_y = -distance * math.cos(elevation)
    cam_z = look_z + distance * math.sin(elevation)
    up = (0.0, math.sin(elevation), math.cos(elevation))
    return f"""
<mujoco model="box_stacking">
  <compiler angle="radian"/>
  <option timestep="0.004" jacobian="dense"/>
  <visual>
    <global offwidth="{image_size}" offheight="{image_size}"/>
    <quality shadowsize="0"/>
    <headlight ambient="0.45 0.45 0.45" diffuse="0.35 0.35 0.35" specular="0 0 0"/>
  </visual>
  <asset>
    <texture name="tex_table" type="2d" builtin="flat" width="8" height="8" rgb1="0.80 0.72 0.60"/>
    <material name="mat_table" texture="tex_table" reflectance="0"/>
    {"".join(assets)}
  </asset>
  <worldbody>
    <light name="sun" directional="true" pos="0 -0.3 1" dir="0 0.3 -1" castshadow="false"
           diffuse="0.45 0.45 0.45"/>
    <!-- a box, not a plane: MuJoCo draws planes finely subdivided, 7x slower here -->
    <geom name="table" type="box" pos="0 0 -0.02" size="4 4 0.02" material="mat_table"/>
    {"".join(pads)}
    <camera name="front" pos="0 {cam_y:.4f} {cam_z:.4f}" xyaxes="1 0 0 0 {up[1]:.4f} {up[2]:.4f}"
            fovy="40"/>
    <body name="gripper" mocap="true" pos="0 0 0.5"/>
    {"".join(bodies)}
  </worldbody>
  <equality>
    {"".join(welds)}
  </equality>
</mujoco>
"""
