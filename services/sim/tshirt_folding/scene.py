"""MJCF of the T-shirt world: one T-shaped flex layer on a table under a top-down camera.

The mesh is a lattice whose grid lines lie on every fold line (the armholes, the side folds,
mid-height), with a centre vertex in every cell and four triangles a cell, so that each crease
follows mesh edges. The texture is one fabric colour with seams, hems, a collar band and a small
chest print, as a plain T-shirt: states show through silhouette and layering, not colour codes.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass

import numpy as np
from PIL import Image, ImageDraw

from shared.tasks.tshirt_folding import TshirtConfig

TEXTURE_FILE = "tshirt.png"
FABRIC = (52, 92, 150)  # mid blue
SEAM = (34, 62, 108)  # stitched seams and hems, darker than the fabric


@dataclass(frozen=True)
class ShirtMesh:
    radius: float = 0.003  # flex collision radius: the shirt lies at z = radius
    mass: float = 0.10
    fovy: float = 40.0  # degrees
    body_columns: int = 12  # cells across the body (even: the middle is a grid line)
    sleeve_columns: int = 2  # cells from an armhole out
    rows: int = 8  # cells up the body (even: mid-height)

    def camera_height(self, task: TshirtConfig) -> float:
        """Height above the table at which one metre spans `pixels_per_metre` of the frame."""
        focal = task.frame / 2 / math.tan(math.radians(self.fovy) / 2)
        return focal / task.pixels_per_metre


def flat_mesh(task: TshirtConfig, mesh: ShirtMesh) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 2) in metres about the body's centre (x right, y up) and triangles (T, 3)."""
    if mesh.body_columns % 2 or mesh.rows % 2:
        raise ValueError("body_columns and rows must be even")
    half_w, half_h = task.body_width / 2, task.body_height / 2
    body = np.linspace(-half_w, half_w, mesh.body_columns + 1)
    sleeve = np.linspace(half_w, half_w + task.sleeve_length, mesh.sleeve_columns + 1)[1:]
    xs = np.concatenate([-sleeve[::-1], body, sleeve])
    ys = np.linspace(-half_h, half_h, mesh.rows + 1)
    dy = ys[1] - ys[0]
    if not _on_grid(task.sleeve_width / dy) or not _on_grid(task.neck_depth / dy):
        raise ValueError("the sleeve's width and the neck's depth must be whole rows")
    if not _on_grid(task.neck_width / (body[1] - body[0])) or not _on_grid(
        task.side_width / (body[1] - body[0])
    ):
        raise ValueError("the neck's width and the side strip must be whole columns")

    def inside(x: float, y: float) -> bool:  # a cell's centre
        if abs(x) > half_w:
            return y > half_h - task.sleeve_width
        return not (abs(x) < task.neck_width / 2 and y > half_h - task.neck_depth)

    index: dict[tuple[int, int], int] = {}
    points: list[tuple[float, float]] = []

    def vertex(i: int, j: int) -> int:
        if (i, j) not in index:
            index[i, j] = len(points)
            points.append((float(xs[i]), float(ys[j])))
        return index[i, j]

    triangles = []
    for j in range(len(ys) - 1):
        for i in range(len(xs) - 1):
            cx, cy = (xs[i] + xs[i + 1]) / 2, (ys[j] + ys[j + 1]) / 2
            if not inside(cx, cy):
                continue
            a, b, c, d = vertex(i, j), vertex(i + 1, j), vertex(i + 1, j + 1), vertex(i, j + 1)
            m = len(points)
            points.append((float(cx), float(cy)))
            # counter-clockwise seen from above: the shirt's front faces the camera
            triangles += [(a, b, m), (b, c, m), (c, d, m), (d, a, m)]
    return np.array(points), np.array(triangles)


def _on_grid(cells: float) -> bool:
    return abs(cells - round(cells)) < 1e-6 and round(cells) >= 1


def extent(task: TshirtConfig) -> tuple[float, float]:
    """Half width (sleeve tip to sleeve tip) and half height of the flat shirt, in metres."""
    return task.body_width / 2 + task.sleeve_length, task.body_height / 2


def shirt_texture(task: TshirtConfig, size: int = 256) -> bytes:
    """PNG over the shirt's bounding box; texcoord (u, v) = ((x + w) / 2w, (y + h) / 2h) with
    (w, h) = `extent`, texture row 0 at v = 0 (the hem)."""
    half_x, half_y = extent(task)
    image = Image.new("RGB", (size, size), FABRIC)
    draw = ImageDraw.Draw(image)

    def px(x: float, y: float) -> tuple[float, float]:  # metres -> texture pixel (row 0: hem)
        return (x + half_x) / (2 * half_x) * size, (y + half_y) / (2 * half_y) * size

    seam = max(1, size // 96)
    hem = max(2, size // 48)
    armhole, top = task.body_width / 2, task.body_height / 2
    low = top - task.sleeve_width
    for sign in (-1, 1):
        # armhole seam, sleeve hem at the cuff, side seam below the sleeve
        draw.line((*px(sign * armhole, low), *px(sign * armhole, top)), fill=SEAM, width=seam)
        cuff = sign * (armhole + task.sleeve_length)
        draw.line((*px(cuff - sign * 0.008, low), *px(cuff - sign * 0.008, top)), SEAM, hem)
        draw.line((*px(sign * armhole, -top), *px(sign * armhole, low)), fill=SEAM, width=seam)
    draw.line((*px(-armhole, -top + 0.01), *px(armhole, -top + 0.01)), fill=SEAM, width=hem)
    # collar band round the neck notch (texture rows grow towards the neck here)
    neck_x, neck_y = task.neck_width / 2, top - task.neck_depth
    band = [px(-neck_x - 0.01, top), px(-neck_x - 0.01, neck_y - 0.01)]
    band += [px(neck_x + 0.01, neck_y - 0.01), px(neck_x + 0.01, top)]
    draw.line(band, fill=(30, 40, 60), width=max(2, size // 40), joint="curve")
    # a small chest print: a light disc with an orange bar
    cx, cy = px(0.0, top - task.neck_depth - 0.05)
    r = size * 0.03 / (2 * half_y)
    draw.ellipse((cx - r, cy - r, cx + r, cy + r), fill=(225, 225, 215))
    draw.rectangle((cx - 0.6 * r, cy - 0.2 * r, cx + 0.6 * r, cy + 0.2 * r), fill=(230, 120, 30))
    buffer = io.BytesIO()
    image.save(buffer, format="PNG")
    return buffer.getvalue()


def build_mjcf(task: TshirtConfig, mesh: ShirtMesh, image_size: int, grip_slots: int) -> str:
    vertices, triangles = flat_mesh(task, mesh)
    half_x, half_y = extent(task)
    points = " ".join(f"{x:.6f} {y:.6f} 0" for x, y in vertices)
    uv = (vertices + np.array([half_x, half_y])) / np.array([2 * half_x, 2 * half_y])
    texcoords = " ".join(f"{u:.6f} {v:.6f}" for u, v in uv)
    elements = " ".join(str(i) for i in triangles.reshape(-1))
    # One gripper that holds a whole flap as a plate (a folding board): run time points each
    # connect at a vertex body (model.eq_obj2id) and switches it on.
    grips = "".join(
        f'<connect name="grip{i}" body1="gripper" body2="world" anchor="0 0 0" '
        'active="false" solref="0.008 1"/>'
        for i in range(grip_slots)
    )
    return f"""
<mujoco model="tshirt_folding">
  <compiler angle="radian"/>
  <option timestep="0.004" integrator="implicitfast" solver="Newton" jacobian="sparse"
          cone="elliptic"/>
  <visual>
    <global offwidth="{image_size}" offheight="{image_size}"/>
    <quality shadowsize="0"/>
    <headlight ambient="0.5 0.5 0.5" diffuse="0.3 0.3 0.3" specular="0 0 0"/>
  </visual>
  <asset>
    <texture name="tex_table" type="2d" builtin="flat" width="8" height="8" rgb1="0.80 0.77 0.72"/>
    <material name="mat_table" texture="tex_table" reflectance="0"/>
    <texture name="tex_shirt" type="2d" file="{TEXTURE_FILE}"/>
    <material name="mat_shirt" texture="tex_shirt" specular="0.05" shininess="0.1"/>
  </asset>
  <worldbody>
    <light name="sun" directional="true" pos="0 0 1" dir="0.25 0.3 -1" castshadow="false"
           diffuse="0.45 0.45 0.45"/>
    <geom name="table" type="plane" size="1 1 0.02" material="mat_table" friction="1.5"/>
    <camera name="top" pos="0 0 {mesh.camera_height(task):.5f}" xyaxes="1 0 0 0 1 0"
            fovy="{mesh.fovy}"/>
    <body name="gripper" mocap="true" pos="0.5 0.5 0.3"/>
    <flexcomp name="shirt" type="direct" dim="2" dof="full" radius="{mesh.radius}"
              mass="{mesh.mass}" pos="0 0 {mesh.radius}" point="{points}" element="{elements}"
              texcoord="{texcoords}" material="mat_shirt">
      <edge equality="true" solref="0.008 1" damping="0.001"/>
      <contact condim="3" friction="1.5" solref="0.004 1" selfcollide="auto"/>
    </flexcomp>
  </worldbody>
  <equality>
    {grips}
  </equality>
</mujoco>
"""
