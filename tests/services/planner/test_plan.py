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
