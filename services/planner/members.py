"""What a roadmap was built from, kept beside it so that it can grow without the images.

`members.safetensors` holds every point's latent and reconstruction errors, each tuple's action
and the true states where known, in the roadmap's point order (z1[0], z2[0], z1[1], ...).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np
from safetensors.numpy import load_file, save_file

from services.encoder.checkpoint import encode_images
from services.encoder.model import VAE
from services.planner.knowing import ERRORS, look_many
from services.planner.roadmap import RoadmapError
from shared.checkpoint import replace_atomically
from shared.dataset import Dataset

MEMBERS = "members.safetensors"


def encode_pairs(model: VAE, data: Dataset) -> tuple[np.ndarray, np.ndarray]:
    """The encoder means of image1 and image2 of every tuple."""
    if model.config.image_size != data.image_size:
        raise ValueError(
            f"the VAE takes {model.config.image_size} px images, "
            f"the dataset has {data.image_size} px"
        )
    return encode_images(model, data.image1)[0], encode_images(model, data.image2)[0]


def interleave(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Rows in the roadmap's point order: first[0], second[0], first[1], ..."""
    return np.stack([first, second], axis=1).reshape(-1, *first.shape[1:])


def tuple_keys(image1: np.ndarray, image2: np.ndarray, u: np.ndarray) -> np.ndarray:
    """(N,) uint64: a 64-bit digest of each tuple's two images and action (never 0)."""
    keys = np.empty(len(u), np.uint64)
    for i in range(len(u)):
        digest = hashlib.blake2b(digest_size=8)
        for part in (image1[i], image2[i], u[i]):
            digest.update(np.ascontiguousarray(part).tobytes())
        keys[i] = max(1, int.from_bytes(digest.digest(), "little"))
    return keys


@dataclass
class Members:
    """The points a roadmap was built from, in its point order."""

    points: np.ndarray  # (2N, D) float32 latents
    errors: np.ndarray  # (2N, 3) float32 reconstruction errors (knowing.ERRORS)
    actions: np.ndarray  # (N, *action shape): each tuple's action, -1 for no-action pairs
    a: np.ndarray  # (N,) uint8: 1 for an action pair
    states: np.ndarray  # (2N, *state shape): the true states where known
    has_state: np.ndarray  # (2N,) uint8: 1 where the recorder knew the state
    experience: np.ndarray  # (N,) uint8: 1 for a tuple grown from experience, 0 for training
    # (N,) uint64: each tuple's content (tuple_keys), so that a copy of experience already grown
    # is known as such; 0 where unknown (members kept before the keys were)
    keys: np.ndarray

    def save(self, folder: Path) -> None:
        arrays = {f.name: np.ascontiguousarray(getattr(self, f.name)) for f in fields(self)}
        replace_atomically(folder / MEMBERS, lambda tmp: save_file(arrays, str(tmp)))

    @classmethod
    def load(cls, folder: Path) -> Members:
        if not (folder / MEMBERS).is_file():
            raise RoadmapError(f"{folder / MEMBERS}: missing")
        try:
            arrays = load_file(str(folder / MEMBERS))
        except Exception as exc:  # safetensors raises its own error types for corrupt files
            raise RoadmapError(f"{folder / MEMBERS}: not a readable safetensors file") from exc
        if "keys" not in arrays and "a" in arrays:
            arrays["keys"] = np.zeros(len(arrays["a"]), np.uint64)
        missing = [f.name for f in fields(cls) if f.name not in arrays]
        if missing:
            raise RoadmapError(f"{folder / MEMBERS}: missing arrays {', '.join(missing)}")
        if arrays["errors"].shape[1:] != (len(ERRORS),):
            raise RoadmapError(
                f"{folder / MEMBERS}: {arrays['errors'].shape[1]} reconstruction errors a point, "
                f"an older knowing's; calibrate the model again with `lsr calibrate`"
            )
        return cls(**{f.name: arrays[f.name] for f in fields(cls)})

    @classmethod
    def encode(cls, model: VAE, data: Dataset, keys: np.ndarray | None = None) -> Members:
        """A dataset's tuples through the (fixed) VAE; `keys`: their tuple_keys, if known."""
        states = (data.state1, data.state2) if data.spec.state is not None else None
        return cls.of_images(model, data.image1, data.image2, data.u, data.a, states, keys)

    @classmethod
    def of_images(
        cls,
        model: VAE,
        image1: np.ndarray,
        image2: np.ndarray,
        u: np.ndarray,
        a: np.ndarray,
        states: tuple[np.ndarray, np.ndarray] | None = None,
        keys: np.ndarray | None = None,
    ) -> Members:
        """Tuples of images through the (fixed) VAE; states where the recorder knew them;
        `keys`: their tuple_keys where the caller has them already."""
        if model.config.image_size != image1.shape[1]:
            raise ValueError(
                f"the VAE takes {model.config.image_size} px images, got {image1.shape[1]} px"
            )
        n = len(u)
        mu, errors = look_many(model, image1, image2)
        (mu1, mu2), (errors1, errors2) = np.split(mu, [n]), np.split(errors, [n])
        return cls(
            points=interleave(mu1, mu2).astype(np.float32),
            errors=interleave(errors1, errors2).astype(np.float32),
            actions=np.asarray(u),
            a=np.asarray(a, np.uint8),
            states=interleave(*states) if states is not None else np.zeros((2 * n, 0), np.int8),
            has_state=np.full(2 * n, states is not None, np.uint8),
            experience=np.zeros(n, np.uint8),
            keys=tuple_keys(image1, image2, u) if keys is None else np.asarray(keys, np.uint64),
        )

    def __add__(self, other: Members) -> Members:
        """Both, this one's points first; the side without states takes the other's shape."""
        first, second = self, other
        if first.states.shape[1:] != second.states.shape[1:]:
            if not second.has_state.any():
                second = second._stateless_like(first)
            elif not first.has_state.any():
                first = first._stateless_like(second)
            else:
                raise ValueError(
                    f"states of shape {first.states.shape[1:]} and {second.states.shape[1:]}"
                )
        return Members(
            *(
                np.concatenate([getattr(first, f.name), getattr(second, f.name)])
                for f in fields(self)
            )
        )

    def _stateless_like(self, other: Members) -> Members:
        """These members (none with a state) with `other`'s state shape, zero-filled."""
        shape = (len(self.points), *other.states.shape[1:])
        return replace(self, states=np.zeros(shape, other.states.dtype))
