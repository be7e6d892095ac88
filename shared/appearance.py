"""How a world's images look: named appearance levels and their seeded draws.

A real camera never sees a scene twice the same way, so a model trained on one fixed rendering
may fail on the first real image. An `Appearance` is one named level (`clean`, `camera`,
`shifted`) of ranges; a seeded generator draws it into a per-episode sample (lights, camera pose,
table: fixed while a scene stays put) and a per-image sample (white balance, exposure, sensor
noise, JPEG: fresh for every picture). `services.sim.appearance` applies them beside any World
(as robosuite's DomainRandomizationWrapper); this module holds no MuJoCo, so that the gateway
and the dataset code can name the levels.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
from typing import Any

import numpy as np

from shared.tasks import get_task
from shared.tasks.base import TaskError

CLEAN = "clean"


class AppearanceError(ValueError):
    """An unknown appearance level; the message names the field and the known levels."""


@dataclass(frozen=True)
class EpisodeRanges:
    """Drawn once per episode (at each world reset); each value is the half-width of a uniform
    range about the default, except the light turn, a cone around the default direction."""

    light_turn_deg: float = 20.0  # light direction within this angle of its default
    light_intensity: float = 0.25  # diffuse light x U(1 - r, 1 + r)
    ambient: float = 0.20  # ambient light x U(1 - r, 1 + r)
    camera_shift_m: float = 0.005  # camera position, each axis
    camera_turn_deg: float = 1.5  # camera roll, pitch and yaw, each
    camera_height: float = 0.0  # camera height above the table x U(1 - r, 1 + r); 0: not drawn
    table_colour: float = 0.05  # table colour x U(1 - r, 1 + r), each channel
    table_texture: float = 0.04  # amplitude of a faint random texture on the table

    def scaled(self, factor: float) -> EpisodeRanges:
        return EpisodeRanges(**{f.name: getattr(self, f.name) * factor for f in fields(self)})


@dataclass(frozen=True)
class ImageRanges:
    """Drawn for every rendered image, after rendering, as a camera's pipeline would."""

    white_balance: float = 0.05  # per-channel gain x U(1 - r, 1 + r)
    exposure: float = 0.10  # overall gain x U(1 - r, 1 + r)
    noise_sigma: float = 2 / 255  # Gaussian sensor noise, in units of full scale
    jpeg_quality: tuple[int, int] = (80, 95)  # encoded and decoded at a quality in this range

    def scaled(self, factor: float) -> ImageRanges:
        low, high = self.jpeg_quality
        return ImageRanges(
            white_balance=self.white_balance * factor,
            exposure=self.exposure * factor,
            noise_sigma=self.noise_sigma * factor,
            jpeg_quality=(max(1, round(high - (high - low) * factor)), high),
        )


@dataclass(frozen=True)
class EpisodeSample:
    """One episode's look: what the modder changes in the scene before rendering."""

    light_tilt: float  # radians between each light's direction and its default
    light_azimuth: float  # radians: which way around the default it tilts
    light_gain: float
    ambient_gain: float
    camera_shift: tuple[float, float, float]  # metres, world frame
    camera_turn: tuple[float, float, float]  # roll, pitch, yaw in radians, camera frame
    table_gain: tuple[float, float, float]
    table_texture: float  # amplitude
    texture_seed: int  # seeds the texture's pattern
    camera_lift: float = 0.0  # share of the camera's height above the table added to it


@dataclass(frozen=True)
class ImageSample:
    """One image's look: what the modder does to the rendered pixels."""

    gains: tuple[float, float, float]  # white balance x exposure, per channel
    noise_sigma: float  # full-scale units
    noise_seed: int
    jpeg_quality: int


def _uniform(rng: np.random.Generator, half: float, size: int | None = None) -> Any:
    return rng.uniform(-half, half, size)


def _gain(rng: np.random.Generator, half: float, size: int | None = None) -> Any:
    return 1.0 + _uniform(rng, half, size)


def _triple(values: np.ndarray) -> tuple[float, float, float]:
    a, b, c = (float(v) for v in values)
    return a, b, c


@dataclass(frozen=True)
class Appearance:
    """A named level: ranges per episode and per image; None for both is `clean` (today's
    rendering, untouched and drawing nothing)."""

    name: str
    episode: EpisodeRanges | None = None
    image: ImageRanges | None = None
    help: str = ""

    @property
    def is_clean(self) -> bool:
        return self.episode is None and self.image is None

    def draw_episode(self, rng: np.random.Generator) -> EpisodeSample | None:
        r = self.episode
        if r is None:
            return None
        # uniform over the cone's solid angle: directions do not bunch up at the default
        cos_max = np.cos(np.deg2rad(r.light_turn_deg))
        return EpisodeSample(
            light_tilt=float(np.arccos(rng.uniform(cos_max, 1.0))),
            light_azimuth=float(rng.uniform(0.0, 2 * np.pi)),
            light_gain=float(_gain(rng, r.light_intensity)),
            ambient_gain=float(_gain(rng, r.ambient)),
            camera_shift=_triple(_uniform(rng, r.camera_shift_m, 3)),
            camera_turn=_triple(np.deg2rad(_uniform(rng, r.camera_turn_deg, 3))),
            table_gain=_triple(_gain(rng, r.table_colour, 3)),
            table_texture=r.table_texture,
            texture_seed=int(rng.integers(2**63)),
            # drawn last, and only where its range is set: the other draws stay as they were
            camera_lift=float(_uniform(rng, r.camera_height)) if r.camera_height else 0.0,
        )

    def draw_image(self, rng: np.random.Generator) -> ImageSample | None:
        r = self.image
        if r is None:
            return None
        white = _gain(rng, r.white_balance, 3)
        exposure = _gain(rng, r.exposure)
        low, high = r.jpeg_quality
        return ImageSample(
            gains=_triple(white * exposure),
            noise_sigma=r.noise_sigma,
            noise_seed=int(rng.integers(2**63)),
            jpeg_quality=int(rng.integers(low, high + 1)),
        )

    def to_json(self) -> dict[str, Any]:
        """What a dataset manifest records: the level and its ranges."""
        return {
            "level": self.name,
            "episode": None if self.episode is None else asdict(self.episode),
            "image": None if self.image is None else asdict(self.image),
        }


_CAMERA = Appearance(
    "camera",
    EpisodeRanges(),
    ImageRanges(),
    help="a camera's variations: lights, camera pose, table, white balance, exposure, noise, JPEG",
)
APPEARANCES: dict[str, Appearance] = {
    CLEAN: Appearance(CLEAN, help="today's rendering, unchanged"),
    "camera": _CAMERA,
    "shifted": replace(
        _CAMERA,
        name="shifted",
        episode=EpisodeRanges().scaled(2),
        image=ImageRanges().scaled(2),
        help="every camera range doubled: for testing generalisation only, never for training",
    ),
}
LEVELS: tuple[str, ...] = tuple(APPEARANCES)


def task_default(task: str) -> str:
    """The appearance a task's data is generated at unless told otherwise: what the task
    declares (`Task.default_look`), else clean."""
    try:
        return get_task(task).default_look
    except TaskError:
        return CLEAN


def get_appearance(name: str, field: str = "appearance") -> Appearance:
    """The level called `name`; AppearanceError naming `field` and the known levels."""
    if name not in APPEARANCES:
        raise AppearanceError(
            f"{field}: unknown appearance level {name!r}; known levels are {', '.join(LEVELS)}"
        )
    return APPEARANCES[name]


def levels_help() -> str:
    """One line for command-line help: every level and what it is for."""
    return "; ".join(f"{a.name}: {a.help}" for a in APPEARANCES.values())


def manifest_appearance(manifest: dict[str, Any]) -> str:
    """The level a dataset was rendered at: `clean` for data recorded before levels existed
    (and for imported data, which says nothing of its look)."""
    recorded = manifest.get("appearance")
    return CLEAN if recorded is None else str(recorded["level"])


def trained_appearance(vae_config: dict[str, Any]) -> str:
    """The level a model was trained at (its VAE's dataset): what it expects to see, and so
    the default for rendering to it. `clean` for models trained before levels existed."""
    return str(vae_config.get("dataset", {}).get("appearance", CLEAN))
