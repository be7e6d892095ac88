import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from services.encoder.model import VAE, VAEConfig
from services.planner.knowing import (
    BATCH,
    EXPOSURE,
    FACTOR,
    MIN_MEMBERS,
    MatchError,
    calibrate,
    check_ends,
    connect,
    errors_of,
    load_calibration,
    look,
    look_many,
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
    # reconstruction errors of the images: whole image, worst patch, missing edges
    n = 2 * len(z1)
    errors = np.column_stack(
        [rng.uniform(0.001, 0.002, n), rng.uniform(0.002, 0.004, n), rng.uniform(0.5, 1.0, n)]
    )
    return roadmap, np.concatenate([z1, z2]), centres, errors


GOOD = np.array(
    [[0.0015, 0.003, 0.7]] * 2
)  # two images the model redraws as well as its training ones


def test_the_thresholds_are_a_factor_over_what_training_images_reach(chain):
    roadmap, latents, _, errors = chain
    calibration = calibrate(roadmap, latents, errors)
    assert calibration.images == len(latents) and calibration.metric == "l1"
    assert calibration.training_quantile <= calibration.training_max
    assert calibration.threshold == pytest.approx(FACTOR * calibration.training_quantile)
    assert calibration.recon_threshold == pytest.approx(FACTOR * calibration.recon_quantile)
    assert calibration.patch_threshold == pytest.approx(FACTOR * calibration.patch_quantile)
    assert calibration.edges_threshold == pytest.approx(FACTOR * calibration.edges_quantile)
    assert 0.5 <= calibration.edges_quantile <= calibration.edges_max <= 1.0
    assert calibration.recon_quantile <= calibration.recon_max <= 0.002
    assert 0.002 <= calibration.patch_quantile <= calibration.patch_max <= 0.004
    nodes = roadmap.nearest_node(latents)
    gaps = np.abs(latents - roadmap.nodes[nodes]).sum(1)
    # 41 images a node: too few for a node's own 0.999 quantile (their maximum); each node's
    # median distance scales the pooled quantile of distance / median
    median = np.array([np.median(gaps[nodes == k]) for k in range(roadmap.num_nodes)])
    shape = np.quantile(gaps / median[nodes], calibration.quantile)
    for node, limit in enumerate(calibration.node_thresholds):
        assert limit == pytest.approx(FACTOR * median[node] * shape)
    assert all(found.known for found in match(roadmap, calibration, latents, errors))


def test_an_image_far_from_every_region_is_not_known_and_names_its_node(chain):
    roadmap, latents, centres, errors = chain
    calibration = calibrate(roadmap, latents, errors)
    near, between = match(
        roadmap, calibration, np.stack([centres[2], (centres[0] + centres[1]) / 2]), GOOD
    )
    assert near.known and near.score < 1
    assert not between.known and between.score > 10 and between.node in (0, 1)
    with pytest.raises(UnknownImageError) as refused:
        check_ends(roadmap, calibration, centres[0], centres[1] / 2, GOOD)
    assert refused.value.end == "goal" and "goal image is unlike" in refused.value.reason
    assert "far from every roadmap region" in refused.value.reason
    assert refused.value.match["start"].known


def test_an_image_the_model_cannot_redraw_is_not_known_even_inside_a_region(chain):
    roadmap, latents, centres, errors = chain
    calibration = calibrate(roadmap, latents, errors)
    inside, badly_drawn = match(
        roadmap,
        calibration,
        np.stack([centres[1], centres[1]]),
        np.array([[0.0015, 0.003, 0.7], [0.05, 0.003, 0.7]]),
    )
    assert inside.known and not badly_drawn.known and badly_drawn.node == inside.node == 1
    assert badly_drawn.score == pytest.approx(0.05 / calibration.recon_threshold)
    # wrong in one place only (a covered corner): the worst patch tells
    _, covered = match(
        roadmap, calibration, np.stack([centres[1]] * 2), GOOD + np.array([0, 0.5, 0])
    )
    assert not covered.known and covered.score == pytest.approx(0.503 / calibration.patch_threshold)
    # close in every pixel, but without the edges the model draws there (a grey cover)
    _, flat = match(roadmap, calibration, np.stack([centres[1]] * 2), GOOD + np.array([0, 0, 9.3]))
    assert not flat.known and flat.score == pytest.approx(10.0 / calibration.edges_threshold)
    for goal_errors, why in (
        ([0.05, 0.003, 0.7], "cannot redraw it"),
        ([0.0015, 0.5, 0.7], "a part of it"),
        ([0.0015, 0.003, 10], "lacks the edges"),
    ):
        with pytest.raises(UnknownImageError, match=why):
            check_ends(
                roadmap, calibration, centres[1], centres[1], np.array([GOOD[0], goal_errors])
            )


def test_a_region_is_judged_by_its_own_spread():
    """A tight region and a broad one: an image as far from the tight one's centre as the broad
    one's images lie from theirs is not known there (one pooled threshold would pass it)."""
    rng = np.random.default_rng(2)
    centres = np.array([[0.0] * 4, [20.0] * 4])
    spreads = (0.02, 1.0)
    z1 = np.concatenate(
        [c + rng.normal(0, s, (60, 4)) for c, s in zip(centres, spreads, strict=True)]
    )
    z2 = np.concatenate(
        [c + rng.normal(0, s, (60, 4)) for c, s in zip(centres, spreads, strict=True)]
    )
    a = np.zeros(120, int)
    a[0], z2[0] = 1, z2[60]  # one action between the regions
    roadmap = build_roadmap(z1, z2, a, RoadmapConfig(min_samples=3))
    latents = np.concatenate([z1, z2])
    calibration = calibrate(roadmap, latents, np.full((240, 3), 0.001))
    tight, broad = (int(roadmap.nearest_node(c)) for c in centres)
    assert calibration.node_thresholds[tight] * 10 < calibration.node_thresholds[broad]
    nodes = roadmap.nearest_node(latents)
    for node in (tight, broad):  # 120 images each (>= MIN_MEMBERS): their own quantile
        mine = np.abs(latents[nodes == node] - roadmap.nodes[node]).sum(1)
        assert len(mine) >= MIN_MEMBERS
        assert calibration.node_thresholds[node] == pytest.approx(
            FACTOR * np.quantile(mine, calibration.quantile)
        )
    offset = np.array([0.5, 0.5, 0, 0])  # L1 1.0: the broad region's images lie this far
    near_tight, near_broad = match(roadmap, calibration, centres + offset, np.full((2, 3), 0.001))
    assert not near_tight.known and near_tight.node == tight
    assert near_broad.known and near_broad.node == broad
    assert calibration.threshold > 1.0  # the pooled threshold would have known both


def test_the_planner_refuses_an_unknown_start_before_searching(chain):
    roadmap, latents, centres, errors = chain
    vae = VAE(VAEConfig(image_size=32, latent_dim=4)).eval()
    planner = VisualPlanner(vae, roadmap, calibrate(roadmap, latents, errors))
    plans = planner.plan_latent(centres[0], centres[2], 4, GOOD)
    assert [p.nodes for p in plans] == [[0, 1, 2]]
    with pytest.raises(UnknownImageError, match="start image"):
        planner.plan_latent(centres[0] + 3.0, centres[2], 4, GOOD)
    with pytest.raises(ValueError, match="reconstruction errors"):
        planner.plan_latent(centres[0], centres[2], 4)
    assert VisualPlanner(vae, roadmap).plan_latent(centres[0] + 3.0, centres[2], 4)  # uncalibrated


def with_island(chain):
    """The chain and an island of two nodes joined by an edge: node 3 just beside node 0 (the
    same state, as a grown roadmap's stale built node), node 4 far away."""
    roadmap, latents, centres, errors = chain
    calibration = calibrate(roadmap, latents, errors)
    island = np.array([centres[0] + 0.12, centres[0] + 40.0], np.float32)
    grown = replace(
        roadmap,
        nodes=np.concatenate([roadmap.nodes, island]),
        node_sizes=np.concatenate([roadmap.node_sizes, [1, 1]]),
        edges=np.concatenate([roadmap.edges, [[3, 4]]]),
        edge_weights=np.concatenate([roadmap.edge_weights, [1]]),
    )
    return grown, replace(calibration, node_thresholds=(1.0,) * 5), centres


def test_ends_in_two_components_plan_from_the_nearest_nodes_that_connect(chain):
    roadmap, calibration, centres = with_island(chain)
    image = centres[0] + 0.08  # nearest the island's node 3, and known at node 0 too
    assert roadmap.nearest_node(image) == 3 and roadmap.component.tolist() == [0, 0, 0, 1, 1]
    assert connect(roadmap, calibration, image, centres[2], 3, 2) == (0, 2)
    assert connect(roadmap, calibration, centres[2], image, 2, 3) == (2, 0)
    assert connect(roadmap, calibration, image, centres[1], 0, 1) == (0, 1)  # joined already
    vae = VAE(VAEConfig(image_size=32, latent_dim=4)).eval()
    plans = VisualPlanner(vae, roadmap, calibration).plan_latent(image, centres[2], 4, GOOD)
    assert [p.nodes for p in plans] == [[0, 1, 2]]
    # known at the island only: nothing to connect, and the planner finds no path
    tight = replace(calibration, node_thresholds=(0.2, 1.0, 1.0, 1.0, 1.0))
    assert connect(roadmap, tight, image, centres[2], 3, 2) == (3, 2)
    assert VisualPlanner(vae, roadmap, tight).plan_latent(image, centres[2], 4, GOOD) == []


def test_a_calibration_round_trips_and_bad_files_are_named(chain, tmp_path):
    roadmap, latents, _, errors = chain
    calibration = calibrate(roadmap, latents, errors)
    save_calibration(calibration, tmp_path)
    assert load_calibration(tmp_path, roadmap) == calibration
    document = json.loads((tmp_path / "match.json").read_text())
    (tmp_path / "match.json").write_text(json.dumps({**document, "metric": "l2"}))
    with pytest.raises(MatchError, match="calibrated in l2"):
        load_calibration(tmp_path, roadmap)
    (tmp_path / "match.json").write_text(json.dumps({**document, "recon_threshold": -1}))
    with pytest.raises(MatchError, match="recon_threshold must be a positive"):
        load_calibration(tmp_path, roadmap)
    (tmp_path / "match.json").write_text(json.dumps({**document, "node_thresholds": [1.0]}))
    with pytest.raises(MatchError, match="one per roadmap node"):
        load_calibration(tmp_path, roadmap)
    (tmp_path / "match.json").write_text(json.dumps({**document, "version": 2}))
    with pytest.raises(MatchError, match="calibrate the model again"):
        load_calibration(tmp_path, roadmap)
    (tmp_path / "match.json").unlink()
    with pytest.raises(MatchError, match="lsr calibrate"):
        load_calibration(tmp_path, roadmap)


def test_look_many_gives_what_look_gives_and_leaves_torch_threads_as_they_were():
    import torch

    vae = VAE(VAEConfig(image_size=16, latent_dim=4)).eval()
    images = np.random.default_rng(0).integers(0, 256, (BATCH * 2 + 7, 16, 16, 3), np.uint8)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        z, errors = look_many(vae, images[:300], images[300:])  # two sets, one after the other
        assert torch.get_num_threads() == 2
        broken = VAE(VAEConfig(image_size=16, latent_dim=4)).eval()
        broken.decode = None  # every batch fails on a worker thread
        with pytest.raises(TypeError):
            look_many(broken, images)
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    z0, errors0 = look(vae, images)
    assert z.shape == z0.shape and errors.shape == errors0.shape
    np.testing.assert_allclose(z, z0, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(errors, errors0, rtol=1e-3, atol=1e-7)
    assert look_many(vae)[0].shape == (0, 4)


def test_a_brighter_image_is_redrawn_as_well_but_a_dark_or_recoloured_one_is_not():
    """The whole-image error forgives a camera's exposure (one gain within EXPOSURE), never a
    change of content, a frame five times too dark, or a colour cast."""
    rng = np.random.default_rng(0)
    drawn = torch.from_numpy(rng.integers(40, 200, (3, 16, 16, 3), dtype=np.uint8))

    def scaled(gains: list[float]) -> torch.Tensor:
        return (drawn.float() * torch.tensor(gains)).clamp(0, 255).round().to(torch.uint8)

    other = torch.from_numpy(rng.integers(40, 200, (3, 16, 16, 3), dtype=np.uint8))
    high = EXPOSURE[1]
    images = [drawn, scaled([high] * 3), scaled([0.2] * 3), scaled([1.0, 1.0, 0.7]), other]
    whole = errors_of(drawn.repeat(len(images), 1, 1, 1), torch.cat(images))[:, 0].reshape(-1, 3)
    assert whole[0].max() == 0
    assert whole[1].max() < 1e-5  # rounding only
    assert whole[2].min() > 0.01  # the gain stops at EXPOSURE[0]
    assert whole[3].min() > 1e-3  # blue at 0.7 of the others
    assert whole[4].min() > 0.01


def test_a_cover_of_the_tables_colour_lacks_the_edges_its_drawing_has():
    """A drawing of faint lines on a grey table: the image itself (with a camera's noise) has
    those edges, a copy with half its area painted the table's grey does not."""
    rng = np.random.default_rng(0)
    drawn = np.full((1, 32, 32, 3), 150, np.uint8)
    drawn[:, ::8] = drawn[:, :, ::8] = 110  # grid lines
    noisy = np.clip(drawn + rng.normal(0, 2.0, drawn.shape), 0, 255).astype(np.uint8)
    covered = noisy.copy()
    covered[:, 16:] = 150
    errors = errors_of(
        torch.from_numpy(np.repeat(drawn, 2, 0)), torch.from_numpy(np.concatenate([noisy, covered]))
    )
    seen, hidden = errors[:, 2]
    assert seen < 1.0 < 3 * seen < hidden
