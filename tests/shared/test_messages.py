import msgpack
import numpy as np
import pytest

from shared.messages import (
    SCHEMA_VERSION,
    EncodeRequest,
    MessageError,
    PathsRequest,
    WireArray,
    pack,
    unpack,
)


@pytest.mark.parametrize("dtype", [np.uint8, np.float32, np.int64])
def test_arrays_round_trip_as_little_endian_bytes(dtype):
    array = (np.arange(24).reshape(2, 3, 4) % 7).astype(dtype)
    wire = WireArray.of(array)
    assert wire.data == array.astype(np.dtype(dtype).newbyteorder("<")).tobytes()
    back = WireArray.model_validate(wire.model_dump()).numpy()
    assert back.dtype == dtype and np.array_equal(back, array)


def test_big_endian_input_is_stored_little_endian():
    array = np.arange(4, dtype=">f4")
    wire = WireArray.of(array)
    assert wire.dtype == "<f4" and np.array_equal(wire.numpy(), array)


def test_array_bytes_must_match_shape_and_dtype():
    with pytest.raises(ValueError, match="bytes for shape"):
        WireArray(shape=[2, 2], dtype="<f4", data=b"\0" * 12)
    with pytest.raises(ValueError):
        WireArray(shape=[2], dtype="<f8", data=b"\0" * 16)  # float64 does not travel
    with pytest.raises(ValueError, match="less than or equal"):  # int64 products would wrap
        WireArray(shape=[2**32, 2**32], dtype="|u1", data=b"")
    with pytest.raises(TypeError, match="cannot go on the wire"):
        WireArray.of(np.zeros(2, dtype=np.float64))


def test_messages_round_trip_through_msgpack_with_their_version():
    request = EncodeRequest(
        task="box_stacking", images=WireArray.of(np.zeros((1, 4, 4, 3), np.uint8))
    )
    payload = pack(request)
    assert msgpack.unpackb(payload)["v"] == SCHEMA_VERSION
    assert unpack(payload, EncodeRequest) == request


def test_unpack_names_what_is_wrong():
    good = pack(
        PathsRequest(
            task="t",
            z_start=WireArray.of(np.zeros(2, np.float32)),
            z_goal=WireArray.of(np.zeros(2, np.float32)),
        )
    )
    other_version = msgpack.packb({**msgpack.unpackb(good), "v": 99})
    with pytest.raises(MessageError, match="schema version 99"):
        unpack(other_version, PathsRequest)
    too_many = msgpack.packb({**msgpack.unpackb(good), "max_plans": 10_000})
    with pytest.raises(MessageError, match=r"PathsRequest\.max_plans"):
        unpack(too_many, PathsRequest)
    with pytest.raises(MessageError, match="not msgpack"):
        unpack(b"\xc1", PathsRequest)
    with pytest.raises(MessageError, match="must be a map"):
        unpack(msgpack.packb([1, 2]), PathsRequest)


@pytest.mark.parametrize(
    "shape",
    [[0, 2**64 - 1], [2**62, 2**62, 0], [2**31, 0], [2**30, 2**30, 0], [0, -1]],
    ids=str,
)
def test_absurd_shapes_are_refused_by_field_not_left_for_numpy(shape):
    payload = msgpack.packb(
        {"v": SCHEMA_VERSION, "task": "t", "images": {"shape": shape, "dtype": "|u1", "data": b""}}
    )
    with pytest.raises(MessageError, match=r"images") as info:
        unpack(payload, EncodeRequest)
    assert info.value.field.startswith("images")


def test_empty_arrays_of_sane_shape_still_travel():
    wire = WireArray(shape=[0, 64, 64, 3], dtype="|u1", data=b"")
    assert wire.numpy().shape == (0, 64, 64, 3)
