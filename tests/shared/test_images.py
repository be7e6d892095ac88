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
