"""Camera-like appearance beside any MuJoCo world: a wrapper World and its modder.

`AppearanceWorld` wraps a World and delegates everything to it; its reset() draws a new
episode sample and its render() changes the scene for that one render (lights, camera pose,
table material and texture), renders, puts every model value back, then post-processes the
pixels (white balance, exposure, sensor noise, JPEG). The world never knows: its physics, its
rng stream and everything read between renders stay exactly as without the wrapper, and at
`clean` the wrapper draws and changes nothing, so its images are the world's, byte for byte.

The appearance stream is seeded from the state of the rng passed to reset() (read, never drawn
from): each data-generation episode, which has its own seed, gets its own look whatever the
number of workers, and the physics draws stay those of `clean`.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
from collections.abc import Iterator
from dataclasses import replace
from typing import Any

import numpy as np
from PIL import Image

from services.sim.rendering import OffscreenCamera, mujoco
from services.sim.workcell import Pinhole
from shared.appearance import (
    CLEAN,
    Appearance,
    EpisodeSample,
    ImageSample,
    get_appearance,
)
from shared.tasks.base import World

STREAM = 0xA7FEA2  # tags the appearance stream apart from any other seeded from the same state
TABLE = "table"  # the geom whose colour and texture vary
TEXEL_M = 0.015  # size of one texel of the faint texture on a flat-coloured table


def appearance_rng(rng: np.random.Generator) -> np.random.Generator:
    """A generator seeded by `rng`'s current state, which it leaves untouched."""
    state = json.dumps(rng.bit_generator.state, sort_keys=True, default=str).encode()
    words = np.frombuffer(hashlib.sha256(state).digest(), dtype=np.uint32)
    return np.random.default_rng([*words.tolist(), STREAM])


def post_process(image: np.ndarray, sample: ImageSample) -> np.ndarray:
    """A camera's pipeline on a rendered uint8 (H, W, 3) image: gains, noise, JPEG."""
    pixels = image.astype(np.float32) * np.asarray(sample.gains, np.float32)
    sigma = 255 * sample.noise_sigma
    noise = np.random.default_rng(sample.noise_seed).normal(0, sigma, image.shape)
    pixels = np.clip(np.rint(pixels + noise.astype(np.float32)), 0, 255).astype(np.uint8)
    buffer = io.BytesIO()
    Image.fromarray(pixels).save(buffer, format="JPEG", quality=sample.jpeg_quality)
    buffer.seek(0)
    with Image.open(buffer) as decoded:
        return np.asarray(decoded.convert("RGB")).copy()


def _only(world: World, name: str, kind: type) -> Any:
    """`world.<name>` when it is a `kind` (the worlds' convention), else its one `kind`."""
    named = getattr(world, name, None)
    if isinstance(named, kind):
        return named
    found = [v for v in vars(world).values() if isinstance(v, kind)]
    if len(found) != 1:
        raise TypeError(
            f"{type(world).__name__}: appearance needs a {kind.__name__} as .{name} or as its "
            f"only one, found {len(found)}"
        )
    return found[0]


def _tilted(direction: np.ndarray, tilt: float, azimuth: float) -> np.ndarray:
    """`direction` turned by `tilt` radians towards `azimuth` around it."""
    d = direction / np.linalg.norm(direction)
    helper = np.eye(3)[int(np.argmin(np.abs(d)))]  # the axis least along d
    u = np.cross(d, helper)
    u /= np.linalg.norm(u)
    v = np.cross(d, u)
    side = np.cos(azimuth) * u + np.sin(azimuth) * v
    return np.cos(tilt) * d + np.sin(tilt) * side


def turn_quat(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rotation in a camera's own frame (x right, y up, looking along -z)."""
    out = np.array([1.0, 0, 0, 0])
    for axis, angle in ((2, roll), (0, pitch), (1, yaw)):
        q = np.zeros(4)
        mujoco.mju_axisAngle2Quat(q, np.eye(3)[axis], angle)
        mujoco.mju_mulQuat(out, out.copy(), q)
    return out


class SceneModder:
    """Changes one MuJoCo model for one render and puts it back: lights, the rendering camera's
    pose, the table's colour and texture. Works on any world with an MjModel, an MjData and an
    OffscreenCamera (as .model, .data, .camera, or its only ones); a geom named `table` is
    optional (without a material its rgba varies, without a texture its material's)."""

    def __init__(self, world: World) -> None:
        self.model: mujoco.MjModel = _only(world, "model", mujoco.MjModel)
        self.data: mujoco.MjData = _only(world, "data", mujoco.MjData)
        self.camera: OffscreenCamera = _only(world, "camera", OffscreenCamera)
        m = self.model
        self._cam = m.camera(self.camera.camera).id
        self._mat = self._tex = -1
        self._geom = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, TABLE)
        if self._geom >= 0:
            self._mat = int(m.geom_matid[self._geom])
        if self._mat >= 0:
            self._tex = int(m.mat_texid[self._mat, mujoco.mjtTextureRole.mjTEXROLE_RGB])
        if self._tex >= 0:
            adr = int(m.tex_adr[self._tex])
            shape = (m.tex_height[self._tex], m.tex_width[self._tex], m.tex_nchannel[self._tex])
            self._texels = slice(adr, adr + int(np.prod(shape)))
            self._tex_shape = tuple(int(n) for n in shape)
            texels = m.tex_data[self._texels].reshape(-1, int(shape[2]))
            self._flat = bool(np.all(texels == texels[0]))

    def _saved(self) -> dict[str, np.ndarray]:
        m, d, h = self.model, self.data, self.model.vis.headlight
        saved = {
            "light_dir": m.light_dir,
            "light_diffuse": m.light_diffuse,
            "light_ambient": m.light_ambient,
            "cam_pos": m.cam_pos,
            "cam_quat": m.cam_quat,
            "geom_rgba": m.geom_rgba,
            "mat_rgba": m.mat_rgba,
            "mat_texrepeat": m.mat_texrepeat,
            "mat_texuniform": m.mat_texuniform,
            "cam_xpos": d.cam_xpos,
            "cam_xmat": d.cam_xmat,
            "light_xpos": d.light_xpos,
            "light_xdir": d.light_xdir,
            "head_ambient": h.ambient,
            "head_diffuse": h.diffuse,
        }
        if self._tex >= 0:
            saved["tex_data"] = m.tex_data[self._texels]
        return {k: np.array(v, copy=True) for k, v in saved.items()}

    def _restore(self, saved: dict[str, np.ndarray]) -> None:
        m, d, h = self.model, self.data, self.model.vis.headlight
        for name in ("light_dir", "light_diffuse", "light_ambient", "cam_pos", "cam_quat"):
            getattr(m, name)[:] = saved[name]
        for name in ("geom_rgba", "mat_rgba", "mat_texrepeat", "mat_texuniform"):
            getattr(m, name)[:] = saved[name]
        for name in ("cam_xpos", "cam_xmat", "light_xpos", "light_xdir"):
            getattr(d, name)[:] = saved[name]
        h.ambient = saved["head_ambient"]
        h.diffuse = saved["head_diffuse"]
        if self._tex >= 0:
            m.tex_data[self._texels] = saved["tex_data"]
            self._upload()

    def _upload(self) -> None:
        # The texture lives on the GPU too; the Renderer keeps its GL and MuJoCo contexts
        # private, and mjr_uploadTexture needs both.
        renderer = self.camera.renderer
        if renderer._gl_context is not None:
            renderer._gl_context.make_current()
        mujoco.mjr_uploadTexture(self.model, renderer._mjr_context, self._tex)

    def _apply(self, s: EpisodeSample) -> None:
        m, h = self.model, self.model.vis.headlight
        for i in range(m.nlight):
            m.light_dir[i] = _tilted(m.light_dir[i], s.light_tilt, s.light_azimuth)
        m.light_diffuse[:] *= s.light_gain
        m.light_ambient[:] *= s.ambient_gain
        h.diffuse = np.asarray(h.diffuse) * s.light_gain
        h.ambient = np.asarray(h.ambient) * s.ambient_gain
        m.cam_pos[self._cam][2] *= 1 + s.camera_lift  # the table's top is z = 0
        m.cam_pos[self._cam] += s.camera_shift
        quat = np.zeros(4)
        mujoco.mju_mulQuat(quat, m.cam_quat[self._cam].copy(), turn_quat(*s.camera_turn))
        m.cam_quat[self._cam] = quat
        mujoco.mj_camlight(m, self.data)  # the scene reads the posed camera and lights
        gain = np.asarray(s.table_gain)
        if self._tex >= 0:
            self._apply_texture(s, gain)
        elif self._mat >= 0:
            m.mat_rgba[self._mat, :3] = np.clip(m.mat_rgba[self._mat, :3] * gain, 0, 1)
        elif self._geom >= 0:
            m.geom_rgba[self._geom, :3] = np.clip(m.geom_rgba[self._geom, :3] * gain, 0, 1)

    def _apply_texture(self, s: EpisodeSample, gain: np.ndarray) -> None:
        m = self.model
        height, width, channels = self._tex_shape
        texels = m.tex_data[self._texels].reshape(height, width, channels).astype(np.float64)
        pattern = np.random.default_rng(s.texture_seed).uniform(-1, 1, (height, width, 1))
        texels[..., :3] *= gain[: min(3, channels)] * (1 + s.table_texture * pattern)
        m.tex_data[self._texels] = np.clip(np.rint(texels), 0, 255).astype(np.uint8).reshape(-1)
        if self._flat:  # a flat colour: repeat it finely, so that the pattern shows
            m.mat_texuniform[self._mat] = 1
            m.mat_texrepeat[self._mat] = 1 / (TEXEL_M * np.array([width, height]))
        self._upload()

    @contextlib.contextmanager
    def applied(self, sample: EpisodeSample) -> Iterator[None]:
        """The scene changed by `sample` inside the block, exactly restored after it."""
        saved = self._saved()
        try:
            self._apply(sample)
            yield
        finally:
            self._restore(saved)

    def render(self, sample: EpisodeSample, camera: OffscreenCamera | None = None) -> np.ndarray:
        """One render by `camera` (default the world's; any other of the same named camera,
        the cell's wider frame, say) with the sample applied."""
        with self.applied(sample):
            return (camera or self.camera).render(self.data)


class AppearanceWorld(World):
    """`world` seen at an appearance level; everything else is the world's own."""

    def __init__(self, world: World, appearance: str | Appearance = CLEAN) -> None:
        self.world = world
        self._modder: SceneModder | None = None
        self._rng = np.random.default_rng([0, STREAM])  # until the first reset
        self._episode: EpisodeSample | None = None
        self.appearance: Appearance = get_appearance(CLEAN)
        self.use(appearance)

    def use(self, appearance: str | Appearance) -> None:
        """Switch level (a served world takes each request's; a benchmark, one of its own
        ranges); the next reset draws it."""
        if isinstance(appearance, str):
            appearance = get_appearance(appearance)
        self.appearance = appearance
        if not self.appearance.is_clean and self._modder is None:
            self._modder = SceneModder(self.world)
        self._episode = self.appearance.draw_episode(self._rng)

    # ----- the world's own, delegated -----
    def __getattr__(self, name: str) -> Any:
        return getattr(self.__dict__["world"], name)

    @property
    def task(self) -> Any:  # type: ignore[override]
        return self.world.task

    @property
    def image_size(self) -> int:  # type: ignore[override]
        return self.world.image_size

    @property
    def episode_length(self) -> int:  # type: ignore[override]
        return self.world.episode_length

    @property
    def settles(self) -> bool:  # type: ignore[override]
        return self.world.settles

    def read_state(self) -> Any:
        return self.world.read_state()

    def execute(self, action: Any, rng: np.random.Generator) -> Any:
        return self.world.execute(action, rng)

    def perturb(self, rng: np.random.Generator) -> Any:
        """The world's perturbation; the episode's look stays (only the image draws change)."""
        return self.world.perturb(rng)

    def demonstrated(self, action: Any, rng: np.random.Generator) -> Any:
        return self.world.demonstrated(action, rng)

    def action_pixels(self, action: Any) -> tuple[tuple[float, float], tuple[float, float]]:
        return self.world.action_pixels(action)

    def close(self) -> None:
        self.world.close()

    # ----- the appearance -----
    def reset(self, state: Any, rng: np.random.Generator) -> Any:
        if not self.appearance.is_clean:  # clean reads nothing, not even the rng's state
            self._rng = appearance_rng(rng)
            self._episode = self.appearance.draw_episode(self._rng)
        return self.world.reset(state, rng)

    def render(self) -> np.ndarray:
        if self.appearance.is_clean:
            return self.world.render()
        return self._look(None)

    def relook(self, camera_only: bool = False) -> None:
        """A fresh draw of the look (lights, table, camera) for the images from now on: the
        same state seen again later, after the light or the camera changed; `camera_only`:
        only the camera's pose drawn again, the light and the table as they were (a camera
        on a robot's head, never twice in one place)."""
        if self.appearance.is_clean:
            return
        drawn = self.appearance.draw_episode(self._rng)
        if camera_only and drawn is not None and self._episode is not None:
            drawn = replace(
                self._episode,
                camera_shift=drawn.camera_shift,
                camera_turn=drawn.camera_turn,
                camera_lift=drawn.camera_lift,
            )
        self._episode = drawn

    def frame(self) -> np.ndarray:
        """The cell's camera frame at this episode's look (the camera's pose draw moves the
        frame as it moves the view: one camera)."""
        camera = getattr(self.world, "frame_camera", None)
        if self.appearance.is_clean or camera is None:
            return self.world.frame() if camera is not None else self.render()
        return self._look(camera)

    def _look(self, camera: OffscreenCamera | None) -> np.ndarray:
        assert self._modder is not None and self._episode is not None
        image = self._modder.render(self._episode, camera)
        sample = self.appearance.draw_image(self._rng)
        return image if sample is None else post_process(image, sample)

    def pinhole(self) -> Pinhole:
        """The camera as this episode's draw posed it (the nominal one at clean): the truth a
        registration is measured against."""
        base = self.world
        name = base.camera.camera
        if self._modder is None or self._episode is None:
            return Pinhole.of(base.model, base.data, name)
        with self._modder.applied(self._episode):
            return Pinhole.of(base.model, base.data, name)

    @property
    def episode_sample(self) -> EpisodeSample | None:
        """This episode's draws (None at clean)."""
        return self._episode
