"""Settled-state libraries on a small cloth (5 x 5 lattice: 41 vertices, folds in a blink)."""

import json
import logging
import shutil

import numpy as np
import pytest

from services.sim.cloth_folding.world import ClothFoldingWorld
from services.sim.settled import STATES, SettledLibrary, stored_orders


@pytest.fixture(scope="module")
def library_dir(tmp_path_factory):
    """The whole library of the 5 x 5 cloth, built and saved once."""
    folder = tmp_path_factory.mktemp("settled") / "cloth5"
    with ClothFoldingWorld(image_size=32, lattice=5, library=[]) as world:
        assert world.library.source is None and not world.library.physics
        world.library.fill(world, progress=False)
        assert world.library.complete(world)
        world.library.save(folder)
    return folder


def test_every_fold_order_of_every_state_is_stored_once(library_dir):
    index = json.loads((library_dir / "library.json").read_text())
    # 1 flat + 4 one-fold + 12 two-fold + 24 three-fold + 24 four-fold orders
    assert len(index["orders"]) == 65 == len(set(map(json.dumps, index["orders"])))
    assert sorted(p.name for p in library_dir.iterdir()) == [
        "MANIFEST.json",
        "library.json",
        "states.safetensors",
    ]


def test_a_cached_reset_reads_back_exactly_for_every_state(library_dir):
    with ClothFoldingWorld(image_size=32, lattice=5, library=[library_dir]) as world:
        assert world.library.source == library_dir and world.library.complete(world)
        rng = np.random.default_rng(0)
        for state in world.task.all_states():
            orders = stored_orders(world.library, state)
            assert len(orders) == len(world.reset_orders(state))
            for order in orders:  # the stored physics comes back bit for bit
                world.load_physics_state(world.library.physics[order])
                assert np.array_equal(world.physics_state(), world.library.physics[order])
                assert world.read_state() == state
            assert world.reset(state, rng) == state  # and put down at a fresh pose
            shares = sorted(world.far_shares().values())
            assert shares[0] < 0.01 and shares[1] > 0.08


def test_a_library_folds_what_it_lacks_on_first_use_and_the_same_physics_each_time(library_dir):
    saved = SettledLibrary.load(library_dir, ClothFoldingWorld(lattice=5, library=[]).task)
    with ClothFoldingWorld(image_size=32, lattice=5, library=[]) as world:
        state = ("top_left", "bottom_right")
        assert world.reset(state, np.random.default_rng(1)) == state
        # the flat cloth, one corner and the two-corner order drawn: nothing else was folded
        assert len(world.library.physics) == 3
        for order, physics in world.library.physics.items():
            assert np.array_equal(physics, saved.physics[order])  # deterministic physics


def test_resets_draw_the_pose_and_the_order_from_the_seed(library_dir):
    with ClothFoldingWorld(image_size=32, lattice=5, library=[library_dir]) as world:
        state = ("top_left", "top_right", "bottom_left")
        images = []
        for seed in (3, 3, 4):
            world.reset(state, np.random.default_rng(seed))
            images.append(world.render())
        assert np.array_equal(images[0], images[1])
        assert not np.array_equal(images[0], images[2])


def test_another_scene_never_loads_the_library(library_dir):
    with ClothFoldingWorld(image_size=32, lattice=7, library=[library_dir]) as world:
        assert world.library.source is None and not world.library.physics


def test_a_changed_library_file_is_refused_and_named(library_dir, tmp_path, caplog):
    copy = tmp_path / "tampered"
    shutil.copytree(library_dir, copy)
    data = bytearray((copy / STATES).read_bytes())
    data[-1] ^= 1
    (copy / STATES).write_bytes(bytes(data))
    with caplog.at_level(logging.WARNING):
        world = ClothFoldingWorld(image_size=32, lattice=5, library=[copy])
    world.close()
    assert world.library.source is None
    assert "states.safetensors" in caplog.text and "sha256 differs" in caplog.text


def test_the_shipped_library_looks_like_physics_to_the_shipped_model():
    """Full size, every state: a cached reset reads back as its state, and the shipped VAE puts
    it in the same roadmap node as the same state reached by physics (noisy clicks, folded one
    corner at a time from a flat cloth at a fresh pose: 15 folds for the 16 states)."""
    import torch

    from services.encoder.checkpoint import encode_images
    from services.planner.build import load_model
    from shared.settings import MODELS_DIR

    model = MODELS_DIR / "cloth_folding"
    vae, _, roadmap, labels = load_model(model)
    torch.set_num_threads(1)
    rng = np.random.default_rng(11)
    with ClothFoldingWorld(image_size=64) as world:
        assert world.library.source == model / "settled" and world.library.complete(world)
        task = world.task
        physical, cached, reached = [], [], {(): None}
        for state in task.all_states():  # each state's parent (one corner fewer) comes first
            if state:
                parent = state[:-1]
                world.load_physics_state(reached[parent])
                move = world.demonstrated(task.moves["fold", state[-1]].action, rng)
                assert world.execute(move, rng) == state
            else:
                assert world.reset_by_physics((), rng) == ()
            reached[state] = world.physics_state()
            physical.append(world.render())
            assert world.reset(state, rng) == state
            cached.append(world.render())
    nodes = roadmap.nearest_node(encode_images(vae, np.stack(physical + cached))[0])
    n = len(task.all_states())
    assert list(nodes[:n]) == list(nodes[n:])
    node_state = [task.array_to_state(s) for s in labels.states]
    assert [node_state[k] for k in nodes[:n]] == list(task.all_states())
