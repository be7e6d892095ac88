import io

import numpy as np
import pytest
from PIL import Image

from shared.images import ImageError, contact_sheet, decode_image, encode_png


def test_png_round_trip():
    image = np.random.default_rng(0).integers(0, 256, (16, 16, 3), dtype=np.uint8)
    assert np.array_equal(decode_image(encode_png(image), size=16), image)


def test_wrong_size_is_named():
    with pytest.raises(ImageError, match="8x8, expected 16x16"):
        decode_image(encode_png(np.zeros((8, 8, 3), np.uint8)), size=16)


def test_not_an_image():
    with pytest.raises(ImageError, match="not a readable"):
        decode_image(b"hello")


def test_gif_is_refused():
    buffer = io.BytesIO()
    Image.new("RGB", (4, 4)).save(buffer, format="GIF")
    with pytest.raises(ImageError, match="GIF"):
        decode_image(buffer.getvalue())


def test_contact_sheet_shape():
    tiles = [np.zeros((10, 12, 3), np.uint8)] * 5
    sheet = contact_sheet(tiles, columns=3, labels=["a"] * 5)
    assert sheet.shape == (2 * (10 + 14) + 2, 3 * 12 + 4, 3)


def test_transparency_is_refused_but_opaque_alpha_converts():
    rgba = np.zeros((8, 8, 4), np.uint8)
    transparent = io.BytesIO()
    Image.fromarray(rgba).save(transparent, format="PNG")
    with pytest.raises(ImageError, match="transparent"):
        decode_image(transparent.getvalue(), 8)
    rgba[..., 3] = 255
    rgba[..., 0] = 200
    opaque = io.BytesIO()
    Image.fromarray(rgba).save(opaque, format="PNG")
    assert decode_image(opaque.getvalue(), 8)[0, 0].tolist() == [200, 0, 0]


def _pillow(data: bytes, at_least: int) -> np.ndarray:
    """What Pillow alone decodes: the reference OpenCV's faster path must equal."""
    with Image.open(io.BytesIO(data)) as img:
        w, h = img.size
        scale = at_least / min(w, h)
        if scale < 1:
            img.draft(img.mode, (round(w * scale), round(h * scale)))
        return np.asarray(img.convert("RGB"))


@pytest.mark.parametrize("mode", ["RGB", "L"])
@pytest.mark.parametrize("side", [40, 96, 200])
def test_a_jpeg_decodes_reduced_to_pillow_s_pixels(mode, side):
    rng = np.random.default_rng(side)
    image = Image.fromarray(rng.integers(0, 256, (side, side + 8, 3), np.uint8)).convert(mode)
    buffer = io.BytesIO()
    image.save(buffer, format="JPEG", quality=90)
    decoded = decode_image(buffer.getvalue(), at_least=24)
    assert decoded.shape[2] == 3 and min(decoded.shape[:2]) >= 24
    assert min(decoded.shape[:2]) < side or side == 40  # reduced in the decoder where it could
    assert np.array_equal(decoded, _pillow(buffer.getvalue(), 24))


@pytest.mark.parametrize("codec", ["JPEG", "PNG"])
def test_exif_orientation_is_not_applied(codec):
    image = np.zeros((32, 32, 3), np.uint8)  # square: turned, it would keep its shape
    image[:, :8] = 255
    exif = Image.Exif()
    exif[0x0112] = 6  # "rotate 90 degrees to view"
    buffer = io.BytesIO()
    Image.fromarray(image).save(buffer, format=codec, exif=exif)
    decoded = decode_image(buffer.getvalue())
    assert decoded[:, :4].mean() > 200 and decoded[:4, 12:].mean() < 50


@pytest.mark.parametrize("codec", ["JPEG", "PNG"])
def test_a_truncated_frame_is_refused(codec):
    rng = np.random.default_rng(0)
    buffer = io.BytesIO()
    Image.fromarray(rng.integers(0, 256, (96, 96, 3), np.uint8)).save(buffer, format=codec)
    with pytest.raises(ImageError, match="truncated"):
        decode_image(buffer.getvalue()[: len(buffer.getvalue()) // 2])
