import json

import numpy as np
import pytest
import torch

from services.encoder.checkpoint import decode_latents, encode_images, load_vae
from services.encoder.model import VAE, VAEConfig
from services.encoder.train import (
    DEFAULT_STEPS,
    SHIFT,
    TrainConfig,
    action_term,
    augment,
    latent_distance,
    schedules,
    train_vae,
)
from services.sim.datagen import GenerateConfig, generate
from shared.checkpoint import CheckpointError


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    out = tmp_path_factory.mktemp("data") / "tiny"
    generate(GenerateConfig(pairs=48, seed=11, image_size=32, workers=1), out, progress=False)
    return out


@pytest.mark.parametrize("size", [32, 64, 128])
def test_shapes(size):
    model = VAE(VAEConfig(image_size=size, latent_dim=8)).eval()
    x = torch.rand(2, 3, size, size)
    with torch.no_grad():
        recon, mu, logvar, z = model(x)
    assert recon.shape == x.shape and mu.shape == logvar.shape == z.shape == (2, 8)
    assert recon.min().item() >= 0 and recon.max().item() <= 1


def test_training_step_in_channels_last_at_128():
    """Training runs channels_last; a oneDNN crash at 128 px was seen with another model."""
    model = VAE(VAEConfig(image_size=128, latent_dim=8)).to(memory_format=torch.channels_last)
    x = torch.rand(2, 3, 128, 128).contiguous(memory_format=torch.channels_last)
    recon, mu, _, _ = model(x)
    ((recon - x).pow(2).sum() + mu.pow(2).sum()).backward()
    assert all(p.grad is not None for p in model.parameters())


def test_image_size_must_be_power_of_two():
    with pytest.raises(ValueError, match="power of two"):
        VAEConfig(image_size=48)


def test_action_term_matches_the_paper():
    z1 = torch.tensor([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    z2 = torch.tensor([[3.0, 4.0], [3.0, 4.0], [30.0, 0.0]])
    a = torch.tensor([0.0, 1.0, 1.0])
    # no-action: d; action: max(0, dm - d); L1 distances 7, 7, 30 with dm 20
    assert float(action_term(z1, z2, a, "l1", 20.0)) == pytest.approx((7 + 13 + 0) / 3)
    assert float(latent_distance(z1[:1], z2[:1], "l2")) == pytest.approx(5.0)
    assert float(latent_distance(z1[:1], z2[:1], "inf")) == pytest.approx(4.0)


def test_schedules():
    cfg = TrainConfig(metric="l1")
    assert schedules(cfg, 0.0) == (0.0, 1.0)
    assert schedules(cfg, 0.5) == (1.0, 2.0)
    assert schedules(cfg, 1.0) == (1.0, 3.0)
    assert schedules(TrainConfig(metric="none"), 0.7)[1] == 0.0
    assert TrainConfig(metric="inf").d_m() == 2.5 and TrainConfig(metric="l2", dm=7).d_m() == 7
    assert TrainConfig(metric="l1").d_m("cloth_folding") == 13.5


def test_bad_train_config():
    with pytest.raises(ValueError, match="metric"):
        TrainConfig(metric="l3")
    with pytest.raises(ValueError, match="dm"):
        TrainConfig(dm=-1.0)
    for bad in ({"steps": 0}, {"epochs": 0}, {"lr_drop": 1.5}, {"clip_grad_norm": 0.0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            TrainConfig(**bad)


def test_run_length_in_steps_whatever_the_data_size():
    assert TrainConfig().total_steps(250) == TrainConfig().total_steps(5000) == DEFAULT_STEPS
    assert TrainConfig(epochs=30).total_steps(5000) == 30 * 79  # the shipped box model's run
    assert TrainConfig(epochs=2, batch_size=16).total_steps(33) == 6


def test_train_is_seeded_and_round_trips(tiny_data, tmp_path):
    cfg = TrainConfig(
        metric="l1", steps=7, batch_size=16, latent_dim=8, monitor_pairs=16, log_every=3
    )
    rec_a = train_vae(tiny_data, tmp_path / "a", cfg, progress=False)
    rec_b = train_vae(tiny_data, tmp_path / "b", cfg, progress=False)
    assert rec_a["loss"] == rec_b["loss"]
    lines = [json.loads(x) for x in (tmp_path / "a" / "log.jsonl").read_text().splitlines()]
    assert [x["step"] for x in lines] == [3, 6, 7]  # every log_every steps, and the last
    assert [x["lr"] for x in lines] == [1e-3, 1e-4, 1e-4]  # dropped after 2/3 of the run
    assert all(x["grad_norm_max"] > 0 and x["clipped_steps"] >= 0 for x in lines)
    model, config = load_vae(tmp_path / "a")
    assert config["train"]["metric"] == "l1" and config["dataset"]["seed"] == 11
    assert config["dataset"]["appearance"] == "clean"  # what serving renders by default
    images = np.zeros((3, 32, 32, 3), np.uint8)
    mu, _ = encode_images(model, images)
    assert mu.shape == (3, 8) and np.allclose(mu[0], mu[1])
    decoded = decode_latents(model, mu)
    assert decoded.shape == (3, 32, 32, 3) and decoded.dtype == np.uint8
    weights = (tmp_path / "a" / "vae.safetensors").read_bytes()
    assert b"pickle" not in weights[:200]


def test_action_term_on_means(tiny_data, tmp_path):
    with pytest.raises(ValueError, match="action_on"):
        TrainConfig(action_on="both")
    cfg = TrainConfig(
        metric="l2", action_on="mean", steps=3, batch_size=16, latent_dim=8, monitor_pairs=16
    )
    record = train_vae(tiny_data, tmp_path / "m", cfg, progress=False)
    assert record["action"] > 0
    assert load_vae(tmp_path / "m")[1]["train"]["action_on"] == "mean"


def test_augment_draws_a_look_per_image_seeded_and_in_range():
    x = torch.full((6, 3, 16, 16), 0.5)
    x[:, :, 6:10, 6:10] = 0.9  # a bright square in the middle
    a, b = (augment(x, torch.Generator().manual_seed(3)) for _ in range(2))
    assert torch.equal(a, b) and a.shape == x.shape
    assert a.min() >= 0 and a.max() <= 1
    assert not torch.equal(a, x)
    means = a.mean((1, 2, 3))
    assert means.std() > 0.01  # each image its own exposure
    # the square moved at most SHIFT pixels: its brightest pixel stays within reach
    peaks = a.mean(1).flatten(1).argmax(1)
    rows, cols = peaks // 16, peaks % 16
    assert (
        (rows >= 6 - SHIFT) & (rows < 10 + SHIFT) & (cols >= 6 - SHIFT) & (cols < 10 + SHIFT)
    ).all()


def test_training_with_augment_keeps_the_recorded_image_as_the_target(tiny_data, tmp_path):
    cfg = TrainConfig(
        metric="l1", steps=3, batch_size=16, latent_dim=8, monitor_pairs=16, augment=True
    )
    record = train_vae(tiny_data, tmp_path / "g", cfg, progress=False)
    assert np.isfinite(record["loss"])
    assert load_vae(tmp_path / "g")[1]["train"]["augment"] is True


def test_baseline_trains_without_action_term(tiny_data, tmp_path):
    cfg = TrainConfig(metric="none", steps=3, batch_size=16, latent_dim=8, monitor_pairs=16)
    record = train_vae(tiny_data, tmp_path / "b", cfg, progress=False)
    assert record["action"] == 0.0 and record["gamma"] == 0.0


def test_load_errors(tmp_path):
    with pytest.raises(CheckpointError, match="not a VAE model folder"):
        load_vae(tmp_path)
    (tmp_path / "config.json").write_text(
        json.dumps({"format": "lsr-vae", "version": 1, "model": {}})
    )
    with pytest.raises(CheckpointError, match=r"vae\.safetensors"):
        load_vae(tmp_path)
