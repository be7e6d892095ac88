"""What the encoder service charges a query of frames against its queue."""

import io

from PIL import Image

from services.encoder.service import megapixels
from shared.messages import FramesRequest, pack


def encoded(size: tuple[int, int], codec: str) -> bytes:
    buffer = io.BytesIO()
    Image.new("RGB", size, "gray").save(buffer, format=codec)
    return buffer.getvalue()


def test_a_query_of_frames_costs_the_pixels_they_decode_to():
    jpeg, png = encoded((4096, 3072), "JPEG"), encoded((400, 400), "PNG")
    request = FramesRequest(task="box_stacking", frames=[jpeg, png])
    # the JPEG decodes reduced by 4 (to 1024 x 768), the PNG whole
    assert megapixels(pack(request)) == (1024 * 768 + 400 * 400) / 1e6
