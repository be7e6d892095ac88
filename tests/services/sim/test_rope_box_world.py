import numpy as np
import pytest

from services.sim.rope_box.world import RopeBoxWorld, swept_angles
from shared.tasks.base import IllegalActionError, WorldError
from shared.tasks.rope_box import Cell, RopeBoxAction


@pytest.fixture(scope="module")
def world():
    w = RopeBoxWorld(image_size=64)
    yield w
    w.close()


def test_every_state_is_laid_out_and_read_back_by_physics(world):
    rng = np.random.default_rng(0)
    for state in world.task.all_states():
        assert world.reset(state, rng) == state
    image = world.render()
    assert image.shape == (64, 64, 3) and image.dtype == np.uint8


def test_every_move_reaches_the_rules_successor(world):
    """From a fresh reset, a third of the 400 moves done physically (every one of them in
    benchmarks/bench_rope_box.py): a push drags the rope, a lift carries it over the pillar;
    the state read back is the one the rules give."""
    rng = np.random.default_rng(1)
    moves = [(s, a) for s in world.task.all_states() for a in world.task.legal_actions(s)]
    assert {a.kind for _, a in moves[::3]} == {"box", "rope"}
    wrong = []
    for state, action in moves[::3]:
        world.reset(state, rng)
        got = world.execute(action, rng)
        if got != world.task.apply(state, action):
            wrong.append((state, action, got))
    assert not wrong


def test_a_walk_of_moves_stays_on_the_rules(world):
    rng = np.random.default_rng(2)
    task = world.task
    s = world.reset(task.all_states()[17], rng)
    for _ in range(30):
        moves = task.legal_actions(s)
        action = moves[rng.integers(len(moves))]
        s2 = world.execute(action, rng)
        assert s2 == task.apply(s, action)
        s = s2


def test_an_illegal_move_raises_and_moves_nothing(world):
    rng = np.random.default_rng(3)
    state = world.task.all_states()[0]
    world.reset(state, rng)
    before = world.data.qpos.copy()
    other = state.orange
    with pytest.raises(IllegalActionError):
        world.execute(RopeBoxAction("box", state.green, other), rng)
    assert np.array_equal(world.data.qpos, before)


def test_the_rope_shape_is_a_nuisance_its_way_past_the_pillars_not(world):
    state = world.task.all_states()[40]
    images = []
    for seed in (4, 5):
        assert world.reset(state, np.random.default_rng(seed)) == state
        images.append(world.render().astype(int))
        assert world.perturb(np.random.default_rng(seed + 10)) == state
    assert np.abs(images[0] - images[1]).sum() > 0


def test_swept_angles_tell_sides_and_turns():
    pillar = np.array([[0.0, 0.0]])
    above = np.array([[-1.0, 0.1], [1.0, 0.1]])
    assert abs(swept_angles(above, pillar)[0] + np.pi) < 0.3  # clockwise past it
    below = np.array([[-1.0, -0.1], [1.0, -0.1]])
    assert abs(swept_angles(below, pillar)[0] - np.pi) < 0.3


def test_a_rope_on_a_pillar_top_is_no_state(world):
    rng = np.random.default_rng(6)
    world.reset(world.task.all_states()[3], rng)
    world.data.xpos[world._vertex_body[12], 2] = world.geometry.pillar_height + 0.01
    with pytest.raises(WorldError, match="not lying on the floor"):
        world.read_state()


def test_actions_point_at_cells_and_pillars(world):
    (px, py), (rx, ry) = world.action_pixels(RopeBoxAction("box", Cell(0, 0), Cell(0, 1)))
    assert px < rx and abs(py - ry) < 1e-6
    (px, py), (qx, qy) = world.action_pixels(RopeBoxAction("rope", Cell(1, 1), Cell(1, 1)))
    assert (px, py) == (qx, qy) and px > world.image_size / 2 and py > world.image_size / 2
