import json

import numpy as np
import pytest

from services.encoder.model import VAE, VAEConfig
from services.planner.knowing import (
    FACTOR,
    MatchError,
    calibrate,
    check_ends,
    load_calibration,
    match,
    save_calibration,
)
from services.planner.plan import VisualPlanner
from services.planner.roadmap import RoadmapConfig, build_roadmap
from shared.plans import UnknownImageError

SPREAD = 0.05


@pytest.fixture(scope="module")
def chain():
    """Three regions 0 - 1 - 2 in 4-D, 40 images each spread about their centre."""
    rng = np.random.default_rng(1)
    centres = np.arange(3)[:, None] * 10.0 * np.ones(4)
    z1, z2, a = [], [], []
    for k in range(3):
        for _ in range(20):
            z1.append(centres[k] + rng.normal(0, SPREAD, 4))
            z2.append(centres[k] + rng.normal(0, SPREAD, 4))
            a.append(0)
        if k < 2:
            z1.append(centres[k] + rng.normal(0, SPREAD, 4))
            z2.append(centres[k + 1] + rng.normal(0, SPREAD, 4))
            a.append(1)
    z1, z2 = np.array(z1), np.array(z2)
    roadmap = build_roadmap(z1, z2, np.array(a), RoadmapConfig(min_samples=3))
    return roadmap, np.concatenate([z1, z2]), centres


def test_the_threshold_is_a_factor_over_what_training_images_reach(chain):
    roadmap, latents, _ = chain
    calibration = calibrate(roadmap, latents)
    assert calibration.images == len(latents) and calibration.metric == "l1"
    assert calibration.training_quantile <= calibration.training_max
    assert calibration.threshold == pytest.approx(FACTOR * calibration.training_quantile)
    assert all(found.known for found in match(roadmap, calibration, latents))


def test_an_image_far_from_every_region_is_not_known_and_names_its_node(chain):
    roadmap, latents, centres = chain
    calibration = calibrate(roadmap, latents)
    near, between = match(
        roadmap, calibration, np.stack([centres[2], (centres[0] + centres[1]) / 2])
    )
    assert near.known and near.score < 1
    assert not between.known and between.score > 10 and between.node in (0, 1)
    with pytest.raises(UnknownImageError) as refused:
        check_ends(roadmap, calibration, centres[0], centres[1] / 2)
    assert refused.value.end == "goal" and "goal image is unlike" in refused.value.reason
    assert refused.value.match["start"].known


def test_the_planner_refuses_an_unknown_start_before_searching(chain):
    roadmap, latents, centres = chain
    vae = VAE(VAEConfig(image_size=32, latent_dim=4)).eval()
    planner = VisualPlanner(vae, roadmap, calibrate(roadmap, latents))
    assert [p.nodes for p in planner.plan_latent(centres[0], centres[2], 4)] == [[0, 1, 2]]
    with pytest.raises(UnknownImageError, match="start image"):
        planner.plan_latent(centres[0] + 3.0, centres[2], 4)
    assert VisualPlanner(vae, roadmap).plan_latent(centres[0] + 3.0, centres[2], 4)  # uncalibrated


def test_a_calibration_round_trips_and_bad_files_are_named(chain, tmp_path):
    roadmap, latents, _ = chain
    calibration = calibrate(roadmap, latents)
    save_calibration(calibration, tmp_path)
    assert load_calibration(tmp_path, roadmap) == calibration
    document = json.loads((tmp_path / "match.json").read_text())
    (tmp_path / "match.json").write_text(json.dumps({**document, "metric": "l2"}))
    with pytest.raises(MatchError, match="calibrated in l2"):
        load_calibration(tmp_path, roadmap)
    (tmp_path / "match.json").write_text(json.dumps({**document, "threshold": -1}))
    with pytest.raises(MatchError, match="positive"):
        load_calibration(tmp_path, roadmap)
    (tmp_path / "match.json").unlink()
    with pytest.raises(MatchError, match="lsr calibrate"):
        load_calibration(tmp_path, roadmap)
