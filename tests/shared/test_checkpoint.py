"""Model folders: atomic writes, manifests, and refusal of what changed since it was sealed."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from services.encoder.checkpoint import WEIGHTS, load_vae, save_vae
from services.encoder.model import VAE, VAEConfig
from services.runtime import ModelInfo
from shared.checkpoint import MANIFEST, CheckpointError, replace_atomically, seal, verify
from shared.settings import SHIPPED_MODEL


def test_seal_then_verify_and_a_changed_or_missing_file_is_named(tmp_path):
    (tmp_path / "a.bin").write_bytes(b"weights")
    (tmp_path / "config.json").write_text("{}")
    assert verify(tmp_path) is False  # unsealed
    seal(tmp_path, ["a.bin", "config.json"])
    assert verify(tmp_path) is True
    (tmp_path / "a.bin").write_bytes(b"weightz")
    with pytest.raises(CheckpointError, match=r"a\.bin: sha256 differs"):
        verify(tmp_path)
    (tmp_path / "a.bin").unlink()
    with pytest.raises(CheckpointError, match=r"a\.bin: listed in MANIFEST\.json but missing"):
        verify(tmp_path)


def test_a_write_that_dies_midway_leaves_the_old_file_and_no_debris(tmp_path):
    path = tmp_path / "weights.bin"
    path.write_bytes(b"old and complete")

    def dies_midway(tmp):
        tmp.write_bytes(b"half of the ne")
        raise KeyboardInterrupt  # as a killed training run would stop

    with pytest.raises(KeyboardInterrupt):
        replace_atomically(path, dies_midway)
    assert path.read_bytes() == b"old and complete"
    assert [p.name for p in tmp_path.iterdir()] == ["weights.bin"]


def test_save_vae_seals_what_it_wrote_and_a_corrupt_model_is_refused_at_load(tmp_path):
    torch.manual_seed(0)
    config = VAEConfig(image_size=32, latent_dim=4)
    save_vae(VAE(config), tmp_path / "vae", {"dataset": {"task": "box_stacking"}})
    assert verify(tmp_path / "vae") and (tmp_path / "vae" / MANIFEST).is_file()
    load_vae(tmp_path / "vae")
    model = tmp_path / "model"
    shutil.copytree(SHIPPED_MODEL, model, ignore=shutil.ignore_patterns("*.png", "*.md"))
    assert ModelInfo.read(model, require_sealed=True).task == "box_stacking"  # shipped: sealed
    weights = model / "vae" / WEIGHTS
    data = bytearray(weights.read_bytes())
    data[-1] ^= 0xFF  # one flipped bit of a float: loads fine, computes nonsense
    weights.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match=r"vae\.safetensors: sha256 differs"):
        ModelInfo.read(model)
    (model / "roadmap" / MANIFEST).unlink()
    shutil.copy(SHIPPED_MODEL / "vae" / WEIGHTS, weights)
    ModelInfo.read(model)  # an unsealed part is served (with a warning) unless required
    with pytest.raises(CheckpointError, match="roadmap not sealed"):
        ModelInfo.read(model, require_sealed=True)


def test_roadmap_save_seals_its_files(tmp_path):
    from services.planner.roadmap import Roadmap

    roadmap = Roadmap.load(SHIPPED_MODEL / "roadmap")
    roadmap.save(tmp_path)
    assert verify(tmp_path)
    assert np.array_equal(Roadmap.load(tmp_path).nodes, roadmap.nodes)
