"""A query's frames decoded and registered half in the encoder's thread, half in its helper
process: the same views as one registration alone, errors naming the request's own field, and
a helper that is gone replaced without losing a query."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from services.encoder.frames import Frames, table_views
from services.sim.worlds import make_world
from shared.registration import Registration
from shared.validation import FieldError


@pytest.fixture(scope="module")
def frames() -> tuple[Registration, list[bytes]]:
    rng = np.random.default_rng(5)
    with make_world("box_stacking", 64, appearance="camera") as world:
        pngs = []
        for _ in range(3):
            world.reset(world.task.sample_state(rng), rng)
            pngs.append(cv2.imencode(".png", world.frame()[..., ::-1])[1].tobytes())
    return Registration(world.task.workcell, 64), pngs


def assert_same_views(views: np.ndarray, expected: np.ndarray) -> None:
    """As registered here, but for the markers' tracking: each process follows the markers from
    the frames it saw last, and corners within a tenth of a pixel move a few levels at edges."""
    difference = np.abs(views.astype(int) - expected)
    assert views.shape == expected.shape
    assert difference.max() <= 8 and difference.mean() < 0.2


@pytest.fixture
def helper(frames):
    registration, _ = frames
    helper = Frames(registration.workcell, 64, nice=0)
    yield helper
    helper.close()


def test_frames_register_in_the_helper_as_here(frames, helper):
    registration, pngs = frames
    expected, reasons = table_views(registration, 0, pngs)
    assert reasons == [None, None, None]  # every frame registered, none refused
    assert helper._process is None  # an encoder that is never sent frames starts no helper
    for query in (pngs[:2], pngs[:2], pngs, pngs[1:2]):  # the first here, starting the helper
        views, refused = helper.views(query)
        assert refused == [None] * len(query)
        start = pngs.index(query[0])
        assert_same_views(views, expected[start : start + len(query)])
        assert helper._process is not None and helper._process.poll() is None


def test_a_frame_that_is_not_an_image_is_named_by_its_index_in_the_query(frames, helper):
    _, pngs = frames
    helper.views(pngs[:2])  # the helper started
    with pytest.raises(FieldError, match=r"^frames\.1: ") as error:
        helper.views([pngs[0], b"not an image"])  # the helper's half
    assert error.value.field == "frames.1"
    with pytest.raises(FieldError, match=r"^frames\.0: "):
        helper.views([b"not an image", pngs[0]])  # this thread's half
    views, _ = helper.views(pngs[:2])  # and the helper still answers
    assert_same_views(views, table_views(frames[0], 0, pngs[:2])[0])


def test_a_helper_that_died_is_replaced_and_no_query_is_lost(frames, helper):
    registration, pngs = frames
    expected, _ = table_views(registration, 0, pngs[:2])
    helper.views(pngs[:2])
    process = helper._process
    assert process is not None
    process.kill()
    process.wait()
    views, _ = helper.views(pngs[:2])  # its half here, and a helper started for the next
    assert_same_views(views, expected)
    assert helper._process is not None and helper._process is not process
    views, _ = helper.views(pngs[:2])
    assert_same_views(views, expected)
