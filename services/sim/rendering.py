"""Offscreen MuJoCo rendering shared by every world: EGL by default, no shadows or reflections."""

from __future__ import annotations

import functools
import os
from collections.abc import Callable

# Without a display only EGL (or OSMesa) can render; choose it before mujoco is imported.
os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco
import numpy as np


def _let_go() -> None:
    """Leave no EGL context current in this thread. MuJoCo's renderer makes its context current
    and keeps it so; a service's worker thread that rendered last then holds it, and freeing
    the renderer from any other thread (at exit, by the garbage collector) fails with
    EGL_BAD_ACCESS. Each render makes it current again."""
    release = _release()
    if release is not None:
        release()


@functools.cache
def _release() -> Callable[[], None] | None:
    """What lets go of this thread's EGL context (None unless MuJoCo renders with EGL), found
    once: renders are a hot path."""
    if os.environ.get("MUJOCO_GL") != "egl":
        return None
    from mujoco import egl
    from OpenGL import EGL

    def release() -> None:
        if egl.EGL_DISPLAY is not None:
            EGL.eglMakeCurrent(
                egl.EGL_DISPLAY, EGL.EGL_NO_SURFACE, EGL.EGL_NO_SURFACE, EGL.EGL_NO_CONTEXT
            )

    return release


class OffscreenCamera:
    """A fixed camera rendering square uint8 images of one model."""

    def __init__(self, model: mujoco.MjModel, camera: str, size: int) -> None:
        if size < 16 or size > 1024:
            raise ValueError(f"image size {size} is out of range 16..1024")
        self.camera = camera
        self.renderer = mujoco.Renderer(model, size, size)
        flags = self.renderer.scene.flags
        flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False  # shadows cost 3-4x
        flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
        flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = False
        _let_go()

    def render(self, data: mujoco.MjData) -> np.ndarray:
        try:
            self.renderer.update_scene(data, camera=self.camera)
            return self.renderer.render().copy()
        finally:
            _let_go()

    def close(self) -> None:
        self.renderer.close()
