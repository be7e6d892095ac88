"""Image codecs and contact sheets: PNG bytes in and out, uint8 RGB arrays everywhere else."""

from __future__ import annotations

import base64
import hashlib
import io
from collections.abc import Sequence

import cv2
import numpy as np
from PIL import Image, ImageDraw

from shared.lru import LruCache

# OpenCV's flags for a JPEG decoded reduced by 1, 2, 4 or 8 in the decoder (PNG: 1 only)
_REDUCED = {
    1: cv2.IMREAD_COLOR,
    2: cv2.IMREAD_REDUCED_COLOR_2,
    4: cv2.IMREAD_REDUCED_COLOR_4,
    8: cv2.IMREAD_REDUCED_COLOR_8,
}


class ImageError(ValueError):
    """Bytes that are not a usable image; the message says why."""


def encode_png(image: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    Image.fromarray(np.asarray(image, dtype=np.uint8)).save(buffer, format="PNG")
    return buffer.getvalue()


def png_b64(image: np.ndarray) -> str:
    """An image as base64 PNG text, as JSON bodies carry it."""
    return base64.b64encode(encode_png(image)).decode("ascii")


class PngCache:
    """base64 PNGs of images seen before: roadmap node images recur in every plan and request."""

    def __init__(self, capacity: int = 4096) -> None:
        self._encoded: LruCache[bytes, str] = LruCache(capacity)

    def b64(self, image: np.ndarray) -> str:
        key = hashlib.blake2b(np.ascontiguousarray(image).tobytes(), digest_size=16).digest()
        key += bytes(str(image.shape), "ascii")
        encoded = self._encoded.get(key)
        if encoded is None:
            encoded = png_b64(image)
            self._encoded.put(key, encoded)
        return encoded


def _opened(
    img: Image.Image,
    size: int | None,
    at_least: int | None,
    max_side: int | None,
    max_pixels: int | None,
) -> None:
    """Every check `decode_image` makes from the header alone, and the JPEG draft it asks."""
    if img.format not in ("PNG", "JPEG"):
        raise ImageError(f"image format {img.format} is not PNG or JPEG")
    if size is not None and img.size != (size, size):
        raise ImageError(f"image is {img.size[0]}x{img.size[1]}, expected {size}x{size}")
    if max_side is not None and not all(16 <= side <= max_side for side in img.size):
        raise ImageError(
            f"image is {img.size[0]}x{img.size[1]}; expected 16 to {max_side} pixels a side"
        )
    if at_least is not None and img.format == "JPEG" and img.mode in ("RGB", "L"):
        w, h = img.size
        scale = at_least / min(w, h)
        if scale < 1:
            img.draft(img.mode, (max(1, round(w * scale)), max(1, round(h * scale))))
    if max_pixels is not None and img.size[0] * img.size[1] > max_pixels:
        raise ImageError(
            f"image is {img.size[0]}x{img.size[1]}: it would decode to "
            f"{img.size[0] * img.size[1]} pixels, at most {max_pixels} are taken "
            "(a JPEG decodes at a reduced scale where it can; a PNG does not)"
        )
    if img.mode not in ("RGB", "RGBA", "L", "P"):
        raise ImageError(f"image mode {img.mode} cannot be converted to RGB safely")


def _opencv(data: bytes, img: Image.Image, full: tuple[int, int]) -> np.ndarray | None:
    """An image opaque by its header through OpenCV's decoders, else None: the same pixels as
    Pillow's (a JPEG reduced by the scale Pillow's draft chose), a quarter faster, and they let
    go of the GIL, so a plan's two frames decode side by side. EXIF orientation is ignored, as
    Pillow does: the frame is what the header's size says."""
    reduced = _REDUCED.get(round(full[0] / img.size[0]))
    if img.mode not in ("RGB", "L") or "transparency" in img.info or reduced is None:
        return None
    array = cv2.imdecode(np.frombuffer(data, np.uint8), reduced | cv2.IMREAD_IGNORE_ORIENTATION)
    if array is None or array.dtype != np.uint8 or array.shape[1::-1] != img.size:
        return None
    return cv2.cvtColor(array, cv2.COLOR_BGR2RGB)  # (faster than _RGB's)


def decode_image(
    data: bytes,
    size: int | None = None,
    at_least: int | None = None,
    max_side: int | None = None,
    max_pixels: int | None = None,
) -> np.ndarray:
    """PNG/JPEG bytes -> uint8 (H, W, 3).

    Refuses other sizes than `size` (checked before any pixel is decoded) and modes that do not
    convert to RGB without loss of what the camera saw: transparency, 16-bit, CMYK and such.
    `at_least`: a JPEG may be decoded scaled down by 2, 4 or 8 (in the decoder, far cheaper than
    decoding it whole) as long as its shorter side stays at least this many pixels.
    `max_pixels`: refuses, before decoding, an image that would decode to more pixels (after
    that scaling): a few kilobytes of PNG can hold a gigabyte of pixels.
    """
    try:
        with Image.open(io.BytesIO(data)) as img:
            full = img.size
            _opened(img, size, at_least, max_side, max_pixels)
            array = _opencv(data, img, full)
            if array is not None:
                return array
            if img.mode == "P" and "transparency" in img.info:
                img = img.convert("RGBA")
            if img.mode == "RGBA" and img.getchannel("A").getextrema()[0] < 255:
                raise ImageError("image has transparent pixels; send an opaque RGB image")
            array = np.asarray(img.convert("RGB"), dtype=np.uint8)
    except ImageError:
        raise
    except Exception as exc:
        raise ImageError(f"not a readable PNG or JPEG image ({exc})") from None
    return array


def image_size(
    data: bytes,
    at_least: int | None = None,
    max_side: int | None = None,
    max_pixels: int | None = None,
) -> tuple[int, int]:
    """(width, height) that `decode_image` would decode `data` to, from its header alone, or
    the ImageError it would raise there: how a gateway refuses an image without decoding it."""
    try:
        with Image.open(io.BytesIO(data)) as img:
            _opened(img, None, at_least, max_side, max_pixels)
            return img.size
    except ImageError:
        raise
    except Exception as exc:
        raise ImageError(f"not a readable PNG or JPEG image ({exc})") from None


def encode_frame(image: np.ndarray) -> bytes:
    """A camera frame as PNG bytes made fast (zlib level 1): lossless, so what a model is given
    of it is what it would be given of the pixels, at a fraction of their bytes on the bus."""
    ok, data = cv2.imencode(
        ".png", np.ascontiguousarray(image[..., ::-1]), [cv2.IMWRITE_PNG_COMPRESSION, 1]
    )
    if not ok:
        raise ImageError(f"could not encode a frame of shape {image.shape} as PNG")
    return data.tobytes()


def contact_sheet(
    images: Sequence[np.ndarray],
    columns: int,
    labels: Sequence[str] | None = None,
    scale: int = 1,
    label_height: int = 14,
) -> np.ndarray:
    """Tile images in a grid, each with an optional caption underneath."""
    if not images:
        raise ValueError("contact_sheet needs at least one image")
    h, w = images[0].shape[:2]
    h, w = h * scale, w * scale
    cell_h = h + (label_height if labels else 0)
    rows = (len(images) + columns - 1) // columns
    sheet = Image.new(
        "RGB", (columns * w + (columns - 1) * 2, rows * cell_h + (rows - 1) * 2), "white"
    )
    draw = ImageDraw.Draw(sheet)
    for i, image in enumerate(images):
        r, c = divmod(i, columns)
        x, y = c * (w + 2), r * (cell_h + 2)
        tile = Image.fromarray(np.asarray(image, dtype=np.uint8))
        if scale != 1:
            tile = tile.resize((w, h), Image.Resampling.NEAREST)
        sheet.paste(tile, (x, y))
        if labels:
            draw.text((x + 2, y + h + 1), labels[i], fill="black")
    return np.asarray(sheet)
