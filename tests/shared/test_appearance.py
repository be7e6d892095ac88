"""Appearance levels: their ranges, their draws and what a dataset records."""

from dataclasses import fields

import numpy as np
import pytest

from shared.appearance import (
    APPEARANCES,
    LEVELS,
    AppearanceError,
    EpisodeRanges,
    ImageRanges,
    get_appearance,
    manifest_appearance,
    trained_appearance,
)


def test_levels_and_the_issue_ranges():
    assert LEVELS == ("clean", "camera", "shifted")
    assert get_appearance("clean").is_clean
    camera = get_appearance("camera")
    assert camera.episode == EpisodeRanges(
        light_turn_deg=20.0,
        light_intensity=0.25,
        ambient=0.20,
        camera_shift_m=0.005,
        camera_turn_deg=1.5,
        table_colour=0.05,
        table_texture=0.04,
    )
    assert camera.image == ImageRanges(0.05, 0.10, 2 / 255, (80, 95))


def test_shifted_doubles_every_range():
    camera, shifted = APPEARANCES["camera"], APPEARANCES["shifted"]
    for f in fields(EpisodeRanges):
        assert getattr(shifted.episode, f.name) == 2 * getattr(camera.episode, f.name)
    for name in ("white_balance", "exposure", "noise_sigma"):
        assert getattr(shifted.image, name) == 2 * getattr(camera.image, name)
    assert shifted.image.jpeg_quality == (65, 95)  # a span of 15 doubled to 30
    assert "never for training" in shifted.help


def test_clean_draws_nothing():
    rng = np.random.default_rng(1)
    before = rng.bit_generator.state
    clean = get_appearance("clean")
    assert clean.draw_episode(rng) is None and clean.draw_image(rng) is None
    assert rng.bit_generator.state == before


@pytest.mark.parametrize("level", ["camera", "shifted"])
def test_draws_stay_within_their_ranges(level):
    appearance = get_appearance(level)
    e, i = appearance.episode, appearance.image
    rng = np.random.default_rng(0)
    episodes = [appearance.draw_episode(rng) for _ in range(500)]
    images = [appearance.draw_image(rng) for _ in range(500)]
    tilt = np.array([s.light_tilt for s in episodes])
    assert tilt.min() >= 0 and tilt.max() <= np.deg2rad(e.light_turn_deg)
    assert tilt.max() > 0.9 * np.deg2rad(e.light_turn_deg)  # the range is used, not just held
    for values, half in (
        ([s.light_gain - 1 for s in episodes], e.light_intensity),
        ([s.ambient_gain - 1 for s in episodes], e.ambient),
        ([s.camera_shift for s in episodes], e.camera_shift_m),
        ([s.camera_turn for s in episodes], np.deg2rad(e.camera_turn_deg)),
        ([np.subtract(s.table_gain, 1) for s in episodes], e.table_colour),
    ):
        spread = np.abs(np.asarray(values))
        assert spread.max() <= half and spread.max() > 0.9 * half
    exposure_and_white = np.array([s.gains for s in images])
    bound = (1 + i.white_balance) * (1 + i.exposure)
    assert exposure_and_white.max() <= bound and exposure_and_white.min() >= 2 - bound - 1e-9
    quality = [s.jpeg_quality for s in images]
    assert min(quality) == i.jpeg_quality[0] and max(quality) == i.jpeg_quality[1]
    assert {s.noise_sigma for s in images} == {i.noise_sigma}


def test_same_seed_same_draws():
    camera = get_appearance("camera")
    a, b = np.random.default_rng(7), np.random.default_rng(7)
    assert camera.draw_episode(a) == camera.draw_episode(b)
    assert camera.draw_image(a) == camera.draw_image(b)


def test_an_unknown_level_is_named():
    with pytest.raises(AppearanceError, match="appearance: unknown appearance level 'foggy'"):
        get_appearance("foggy")
    with pytest.raises(AppearanceError, match="known levels are clean, camera, shifted"):
        get_appearance("CAMERA")


def test_datasets_and_models_before_levels_are_clean():
    assert manifest_appearance({"task": "box_stacking"}) == "clean"
    assert manifest_appearance({"appearance": get_appearance("camera").to_json()}) == "camera"
    assert trained_appearance({"dataset": {"task": "box_stacking"}}) == "clean"
    assert trained_appearance({"dataset": {"appearance": "camera"}}) == "camera"
