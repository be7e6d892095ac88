"""MJCF of the cloth-folding world: a flex cloth on a table under a top-down camera.

The mesh is an n x n lattice plus a centre vertex in every square, four triangles a square, so
that creases along rows, columns and both diagonals follow mesh edges (a plain grid crumples
when folded across its other diagonal). Geometry lives in `ClothGeometry`; the camera is placed
so that the flat cloth spans `cloth_pixels` of the task's action frame.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass

import numpy as np
from PIL import Image, ImageDraw

from shared.tasks.cloth_folding import CORNER_DIRECTIONS, ClothFoldingConfig

TEXTURE_FILE = "cloth.png"
PAD_SLOTS = 9  # connect constraints of the gripper pad: a vertex and its mesh neighbours


@dataclass(frozen=True)
class ClothGeometry:
    side: float = 0.28  # metres
    lattice: int = 9  # vertices along a side (odd, so that the centre and mid-edges are vertices)
    radius: float = 0.003  # flex collision radius: the cloth lies at z = radius
    mass: float = 0.06
    fovy: float = 40.0  # degrees

    def __post_init__(self) -> None:
        if self.lattice < 3 or self.lattice % 2 == 0:
            raise ValueError(f"lattice must be odd and at least 3, got {self.lattice}")

    @property
    def spacing(self) -> float:
        return self.side / (self.lattice - 1)

    def camera_height(self, task: ClothFoldingConfig) -> float:
        """Camera height above the table at which the flat cloth spans `cloth_pixels`."""
        visible = self.side * task.frame / task.cloth_pixels
        return visible / 2 / math.tan(math.radians(self.fovy) / 2)


def flat_mesh(geometry: ClothGeometry) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 2) in metres about the centre (x right, y up) and triangles (T, 3)."""
    n, half = geometry.lattice, geometry.side / 2
    ticks = np.linspace(-half, half, n)
    lattice = np.array([(x, y) for y in ticks for x in ticks])
    mids = (ticks[:-1] + ticks[1:]) / 2
    centres = np.array([(x, y) for y in mids for x in mids])
    triangles = []
    for sy in range(n - 1):
        for sx in range(n - 1):
            a, b = sy * n + sx, sy * n + sx + 1
            c, d = (sy + 1) * n + sx + 1, (sy + 1) * n + sx
            m = n * n + sy * (n - 1) + sx
            # counter-clockwise seen from above: the cloth's front faces the camera
            triangles += [(a, b, m), (b, c, m), (c, d, m), (d, a, m)]
    return np.concatenate([lattice, centres]), np.array(triangles)


# Quadrant colours as the camera sees them; the flap of each corner (beyond its fold line) is a
# lighter shade with stripes along x, so a folded flap shows which corner it is and, by its
# stripes turned 90 degrees, that its back is up.
_COLOURS: dict[str, tuple[int, int, int]] = {
    "top_left": (40, 80, 220),
    "top_right": (235, 200, 30),
    "bottom_left": (215, 45, 40),
    "bottom_right": (40, 160, 70),
}


def cloth_texture(size: int = 256) -> bytes:
    """PNG of the cloth's texture; texcoord (u, v) = ((x + side/2) / side, (y + side/2) / side)."""
    image = Image.new("RGB", (size, size))
    pixels = np.zeros((size, size, 3), np.uint8)
    coords = (np.arange(size) + 0.5) / size * 2 - 1  # -1 .. 1 across the cloth
    x = coords[None, :].repeat(size, 0)
    y = coords[:, None].repeat(size, 1)  # texture row 0 is v = 0, the cloth edge at y = -1
    for corner, (dx, dy) in CORNER_DIRECTIONS.items():
        sx, sy = dx, -dy  # image-down rows -> world-up y
        quadrant = (np.sign(x) == sx) & (np.sign(y) == sy)
        flap = quadrant & (sx * x + sy * y > 1)
        colour = np.array(_COLOURS[corner])
        pixels[quadrant] = colour
        light = (colour + 0.45 * (255 - colour)).astype(np.uint8)
        stripes = flap & (np.floor(y * 12) % 2 == 0)
        pixels[flap] = light
        pixels[stripes] = (colour * 0.8).astype(np.uint8)
    image = Image.fromarray(pixels)
    draw = ImageDraw.Draw(image)
    last = size - 1
    dark = (30, 30, 30)
    draw.rectangle((0, 0, last, last), outline=dark, width=max(2, size // 64))
    for a, b in (((0, size / 2), (size / 2, 0)), ((size / 2, 0), (last, size / 2))):
        draw.line((*a, *b), fill=dark, width=max(1, size // 128))
    for a, b in (((0, size / 2), (size / 2, last)), ((size / 2, last), (last, size / 2))):
        draw.line((*a, *b), fill=dark, width=max(1, size // 128))
    buffer = io.BytesIO()
    image.save(buffer, format="PNG")
    return buffer.getvalue()


def build_mjcf(task: ClothFoldingConfig, geometry: ClothGeometry, image_size: int) -> str:
    g = geometry
    vertices, triangles = flat_mesh(g)
    points = " ".join(f"{x:.6f} {y:.6f} 0" for x, y in vertices)
    uv = (vertices + g.side / 2) / g.side
    texcoords = " ".join(f"{u:.6f} {v:.6f}" for u, v in uv)
    elements = " ".join(str(i) for i in triangles.reshape(-1))
    # One gripper whose pad holds up to PAD_SLOTS vertices; run time points each connect at a
    # vertex body (model.eq_obj2id) and switches it on.
    pads = "".join(
        f'<connect name="pad{i}" body1="gripper" body2="world" anchor="0 0 0" '
        'active="false" solref="0.008 1"/>'
        for i in range(PAD_SLOTS)
    )
    return f"""
<mujoco model="cloth_folding">
  <compiler angle="radian"/>
  <option timestep="0.004" integrator="implicitfast" solver="Newton" jacobian="sparse"
          cone="elliptic"/>
  <visual>
    <global offwidth="{image_size}" offheight="{image_size}"/>
    <quality shadowsize="0"/>
    <headlight ambient="0.55 0.55 0.55" diffuse="0.35 0.35 0.35" specular="0 0 0"/>
  </visual>
  <asset>
    <texture name="tex_table" type="2d" builtin="flat" width="8" height="8" rgb1="0.78 0.75 0.70"/>
    <material name="mat_table" texture="tex_table" reflectance="0"/>
    <texture name="tex_cloth" type="2d" file="{TEXTURE_FILE}"/>
    <material name="mat_cloth" texture="tex_cloth" specular="0" shininess="0"/>
  </asset>
  <worldbody>
    <light name="sun" directional="true" pos="0 0 1" dir="0 0 -1" castshadow="false"
           diffuse="0.35 0.35 0.35"/>
    <geom name="table" type="plane" size="1 1 0.02" material="mat_table" friction="1.5"/>
    <camera name="top" pos="0 0 {g.camera_height(task):.5f}" xyaxes="1 0 0 0 1 0"
            fovy="{g.fovy}"/>
    <body name="gripper" mocap="true" pos="0.5 0.5 0.3"/>
    <flexcomp name="cloth" type="direct" dim="2" dof="full" radius="{g.radius}" mass="{g.mass}"
              pos="0 0 {g.radius}" point="{points}" element="{elements}" texcoord="{texcoords}"
              material="mat_cloth">
      <edge equality="true" solref="0.008 1" damping="0.001"/>
      <contact condim="3" friction="1.5" solref="0.004 1" selfcollide="auto"/>
    </flexcomp>
  </worldbody>
  <equality>
    {pads}
  </equality>
</mujoco>
"""
