import numpy as np
import pytest

import services.planner.plan as plan_module
from services.encoder.model import VAE, VAEConfig
from services.planner.plan import VisualPlanner
from services.planner.roadmap import RoadmapConfig, build_roadmap


@pytest.fixture(scope="module")
def planner():
    """A chain of 4 regions 0 - 1 - 2 - 3 in an 8-D latent space, and an untrained VAE."""
    rng = np.random.default_rng(0)
    centres = np.arange(4)[:, None] * 10.0 * np.ones(8)
    z1, z2, a = [], [], []
    for k in range(4):
        for _ in range(5):  # no-action pairs inside a region
            z1.append(centres[k] + rng.normal(0, 0.01, 8))
            z2.append(centres[k] + rng.normal(0, 0.01, 8))
            a.append(0)
        if k < 3:  # action pairs to the next region
            z1.append(centres[k] + rng.normal(0, 0.01, 8))
            z2.append(centres[k + 1] + rng.normal(0, 0.01, 8))
            a.append(1)
    roadmap = build_roadmap(np.array(z1), np.array(z2), np.array(a), RoadmapConfig())
    assert roadmap.num_nodes == 4
    return VisualPlanner(VAE(VAEConfig(image_size=32, latent_dim=8)).eval(), roadmap), centres


def test_plan_latent_walks_the_chain(planner):
    vp, centres = planner
    plans = vp.plan_latent(centres[0] + 0.1, centres[3] - 0.1, max_paths=4)
    assert [p.nodes for p in plans] == [[0, 1, 2, 3]]
    assert plans[0].latents.shape == (4, 8)


def test_each_node_is_decoded_once(planner, monkeypatch):
    vp, _ = planner
    calls = []
    real = plan_module.decode_latents

    def counting(vae, z):
        calls.append(len(z))
        return real(vae, z)

    monkeypatch.setattr(plan_module, "decode_latents", counting)
    vp._images.clear()
    first = vp.node_images([0, 1, 2])
    second = vp.node_images([2, 3, 0])
    assert calls == [3, 1]
    assert np.array_equal(first[0], second[2]) and first[0].shape == (32, 32, 3)


@pytest.mark.parametrize(
    "images",
    [
        np.zeros((2, 64, 64, 3), np.uint8),
        np.zeros((2, 32, 32), np.uint8),
        np.zeros((2, 32, 32, 3), np.float32),
    ],
)
def test_wrong_images_are_refused(planner, images):
    vp, _ = planner
    with pytest.raises(ValueError, match=r"uint8 of shape \(N, 32, 32, 3\)"):
        vp.encode(images)


def test_a_closed_loop_keeps_its_place_where_the_image_is_known_there(planner):
    """With `expect`, the plan starts at the node the last step was meant to reach, if the
    image is known there too; otherwise at the nearest node."""
    from dataclasses import replace

    from services.planner.knowing import calibrate

    vp, centres = planner
    roadmap = vp.roadmap
    errors = np.full((2, 3), 1e-3)
    latents = np.concatenate([roadmap.nodes] * 2).astype(np.float64)
    known = calibrate(roadmap, latents + 0.01, np.full((len(latents), 3), 1e-3))
    wide = replace(known, node_thresholds=(1.0, 100.0, 1.0, 1.0))  # node 1 knows far around
    calibrated = VisualPlanner(vp.vae, roadmap, wide)
    start, goal = centres[0] + 0.05, centres[3]  # nearest node 0, within node 1's bound too
    assert calibrated.plan_latent(start, goal, 4, errors)[0].nodes[0] == 0
    assert calibrated.plan_latent(start, goal, 4, errors, expect=1)[0].nodes == [1, 2, 3]
    assert calibrated.plan_latent(start, goal, 4, errors, expect=2)[0].nodes[0] == 0  # not there
