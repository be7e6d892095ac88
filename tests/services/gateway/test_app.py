"""Gateway pieces that need no network: image decoding, the body limit, error mapping."""

import base64
import io

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from PIL import Image, ImageFile
from pydantic import ValidationError

from services.gateway.app import BodyLimit, error_body
from services.gateway.middleware import Admission
from services.gateway.planning import decode_b64_image, image_input
from services.gateway.schemas import PlanRequest
from shared.bus import RemoteError, ServiceUnavailable
from shared.messages import ErrorReply
from shared.validation import FRAME_DETAIL, FieldError, decode_frame, frame_size


def png_b64(size: int, mode: str = "RGB") -> str:
    buffer = io.BytesIO()
    Image.new(mode, (size, size), "red").save(buffer, format="PNG")
    return base64.b64encode(buffer.getvalue()).decode()


def test_images_decode_from_base64_with_or_without_a_data_url():
    assert decode_b64_image("start.image", png_b64(8), 8).shape == (8, 8, 3)
    assert decode_b64_image("start.image", "data:image/png;base64," + png_b64(8), 8)[0, 0, 0] == 255


def test_an_image_at_the_models_size_is_decoded_a_frame_goes_on_as_its_bytes():
    assert image_input("start.image", png_b64(64), 64).shape == (64, 64, 3)
    frame = image_input("start.image", png_b64(320), 64)
    assert frame == base64.b64decode(png_b64(320))  # the client's bytes, for the encoder
    with pytest.raises(FieldError, match="expected 16 to 4096 pixels a side"):
        image_input("start.image", png_b64(8), 64)


def test_a_frame_that_would_decode_beyond_the_cap_is_refused_before_decoding(monkeypatch):
    bomb = png_b64(4096)  # 4096 x 4096 of one colour: 50 kB of PNG, 50 MB of pixels
    assert len(bomb) < 100_000
    decoded = []
    monkeypatch.setattr(ImageFile.ImageFile, "load", lambda img: decoded.append(img.size))
    with pytest.raises(FieldError, match=r"start.image.*4096x4096: it would decode to 16777216"):
        image_input("start.image", bomb, 64)
    with pytest.raises(FieldError, match=r"frames.0.*4096x4096: it would decode to 16777216"):
        decode_frame("frames.0", base64.b64decode(bomb))  # the encoder's check, the same
    assert decoded == []  # refused from its header


def test_a_large_jpeg_frame_decodes_reduced_but_keeps_its_detail():
    buffer = io.BytesIO()
    Image.new("RGB", (4096, 3072), "red").save(buffer, format="JPEG", quality=80)
    # by 4 in the decoder: by 8 the shorter side would fall below FRAME_DETAIL
    assert frame_size("start.image", buffer.getvalue()) == (1024, 768)
    assert decode_frame("frames.0", buffer.getvalue()).shape == (768, 1024, 3)
    assert 768 // 2 < FRAME_DETAIL <= 768


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("@@@", "not valid base64"),
        (base64.b64encode(b"hello").decode(), "not a readable"),
        (png_b64(9), "expected 8x8"),
    ],
)
def test_bad_images_name_their_field(text, message):
    with pytest.raises(FieldError, match=message) as info:
        decode_b64_image("goal.image", text, 8)
    assert info.value.field == "goal.image"


def test_plan_requests_need_exactly_one_of_image_and_state():
    with pytest.raises(ValidationError, match="exactly one"):
        PlanRequest.model_validate(
            {"task": "box_stacking", "start": {}, "goal": {"state": {"stacks": [[], [], []]}}}
        )


def test_errors_map_to_statuses():
    assert error_body(FieldError("start.state", "bad"))[0] == 422
    assert error_body(FieldError("start.state", "bad"))[1][0]["loc"] == ["body", "start", "state"]
    assert error_body(ServiceUnavailable("apn", "gone")) == (503, "apn service unavailable: gone")
    internal = RemoteError("sim", ErrorReply(code="internal", message="boom"))
    assert error_body(internal)[0] == 502
    assert error_body(KeyError("bug")) is None  # a bug is not dressed up as a known error


def test_body_limit_refuses_declared_and_streamed_bodies():
    app = FastAPI()

    @app.post("/echo")
    async def echo(body: dict) -> dict:
        return body

    app.add_middleware(BodyLimit, limit=100)
    client = TestClient(app)
    assert client.post("/echo", json={"a": 1}).status_code == 200
    assert client.post("/echo", json={"a": "x" * 200}).status_code == 413

    def chunks():
        yield b'{"a": "'
        yield b"x" * 200
        yield b'"}'

    reply = client.post("/echo", content=chunks(), headers={"content-type": "application/json"})
    assert reply.status_code == 413 and "100 bytes" in reply.json()["detail"]


def test_admission_shares_by_declared_body_size():
    light, heavy, every = (
        Admission(None, frozenset({"/plan"}), 1, 1, 1.0, heavy=kind, light_bytes=1000)
        for kind in (False, True, None)
    )

    def scope(path: str, length: bytes | None) -> dict:
        headers = [] if length is None else [(b"content-length", length)]
        return {"type": "http", "path": path, "headers": headers}

    assert light.takes(scope("/plan", b"1000")) and not heavy.takes(scope("/plan", b"1000"))
    assert heavy.takes(scope("/plan", b"1001")) and not light.takes(scope("/plan", b"1001"))
    assert heavy.takes(scope("/plan", None))  # a body of undeclared length: frames, maybe
    assert every.takes(scope("/plan", b"5")) and every.takes(scope("/plan", None))
    assert not any(a.takes(scope("/tasks", b"5")) for a in (light, heavy, every))
