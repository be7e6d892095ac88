"""The cloth world on a small lattice (7 x 7, 85 vertices): the same physics in a fraction of the
time; the full-size cloth only where a test needs it."""

import numpy as np
import pytest

from services.sim.cloth_folding.scene import flat_mesh
from services.sim.cloth_folding.world import ClothFoldingWorld
from shared.tasks.base import IllegalActionError, InvalidActionError, InvalidStateError, WorldError
from shared.tasks.cloth_folding import ClothAction, Pixel


@pytest.fixture(scope="module")
def cloth():
    w = ClothFoldingWorld(image_size=32, lattice=7)
    yield w
    w.close()


def test_every_state_is_reached_by_physics_and_read_back_exactly(cloth):
    rng = np.random.default_rng(0)
    images = {}
    for state in cloth.task.all_states():
        assert cloth.reset(state, rng) == state
        shares = sorted(cloth.far_shares().values())
        assert shares[0] < 0.01 and shares[1] > 0.08  # its own reference, then the nearest other
        images[state] = cloth.render()
        assert images[state].shape == (32, 32, 3) and images[state].dtype == np.uint8
    flat = images[()].astype(int)
    assert all(np.abs(flat - img).sum() > 500 for s, img in images.items() if s)


def test_clicks_of_the_task_land_on_the_cloth_where_the_world_sees_it(cloth):
    cloth.reset((), np.random.default_rng(1))
    for (kind, _), move in cloth.task.moves.items():
        if kind == "fold":
            vertex = cloth.grasp_vertex(move.action.pick, 0)
            x, y = flat_mesh(cloth.geometry)[0][vertex]
            assert abs(x) == abs(y) == cloth.geometry.side / 2  # the corner itself
    centre = cloth.to_pixels(np.array([[0.0, 0.0, 0.0]]))[0]
    assert np.allclose(centre, cloth.task.config.frame / 2)


def test_fold_then_unfold_with_noisy_clicks(cloth):
    rng = np.random.default_rng(2)
    task = cloth.task
    state = cloth.reset(("top_right",), rng)
    for kind, corner in (
        ("fold", "bottom_left"),
        ("unfold", "top_right"),
        ("unfold", "bottom_left"),
    ):
        action = cloth.demonstrated(task.moves[kind, corner].action, rng)
        expected = task.apply(state, action)
        state = cloth.execute(action, rng)
        assert state == expected
    assert state == ()


def test_an_action_no_move_matches_leaves_the_cloth_as_it_was(cloth):
    rng = np.random.default_rng(3)
    cloth.reset(("top_left",), rng)
    before = cloth.vertices()
    fold = cloth.task.moves["fold", "top_left"].action
    with pytest.raises(IllegalActionError, match="already folded"):
        cloth.execute(fold, rng)
    with pytest.raises(IllegalActionError, match="no fold or unfold matches"):
        cloth.execute(ClothAction(Pixel(128, 60), Pixel(128, 128), 0), rng)
    assert np.array_equal(cloth.vertices(), before)


def test_a_pick_that_hits_no_cloth_or_no_top_layer(cloth):
    cloth.reset((), np.random.default_rng(4))
    with pytest.raises(InvalidActionError, match=r"action.pick: pixel \(3, 250\) hits no cloth"):
        cloth.grasp_vertex(Pixel(3, 250), 0)
    with pytest.raises(InvalidActionError, match="single layer"):
        cloth.grasp_vertex(Pixel(128, 128), 1)


def test_a_cloth_that_matches_no_state_names_the_nearest(cloth):
    cloth.reset((), np.random.default_rng(5))
    points = cloth.vertices()
    points[:, :2] *= 0.75  # shrunk: no state looks like this
    cloth._set_vertices(points)
    shares = cloth.far_shares()
    nearest = min(shares, key=shares.__getitem__)
    assert shares[nearest] > 0.05
    with pytest.raises(WorldError, match="matches no state: nearest is") as error:
        cloth.read_state()
    assert str(cloth.task.state_to_json(nearest)) in str(error.value)


def test_no_action_perturbation_keeps_the_state_and_changes_the_image(cloth):
    rng = np.random.default_rng(6)
    state = cloth.reset(("bottom_right",), rng)
    before = cloth.render()
    assert cloth.perturb(rng) == state
    assert np.abs(cloth.render().astype(int) - before).sum() > 0


def test_same_seed_same_image(cloth):
    images = []
    for _ in range(2):
        cloth.reset(("top_left", "bottom_right"), np.random.default_rng(7))
        images.append(cloth.render())
    assert np.array_equal(*images)


def test_invalid_states_are_refused_before_any_physics(cloth):
    with pytest.raises(InvalidStateError, match="appears twice"):
        cloth.reset(("top_left", "top_left"), np.random.default_rng(0))


def test_full_size_cloth_folds_and_unfolds_a_corner():
    with ClothFoldingWorld(image_size=64) as world:
        rng = np.random.default_rng(8)
        assert world.reset((), rng) == ()
        moves = world.task.moves
        assert world.execute(world.demonstrated(moves["fold", "top_left"].action, rng), rng) == (
            "top_left",
        )
        assert world.execute(world.demonstrated(moves["unfold", "top_left"].action, rng), rng) == ()
