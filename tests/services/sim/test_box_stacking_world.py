import numpy as np
import pytest

from services.sim.box_stacking.world import BoxStackingWorld
from shared.tasks.base import IllegalActionError, InvalidStateError, WorldError
from shared.tasks.box_stacking import Cell, Move


def test_every_state_renders_and_reads_back(world):
    rng = np.random.default_rng(0)
    for state in world.task.all_states():
        assert world.reset(state, rng) == state
        image = world.render()
        assert image.shape == (64, 64, 3) and image.dtype == np.uint8


def test_noise_changes_the_image_but_not_the_state(world):
    state = world.task.all_states()[100]
    images = []
    for seed in (1, 2):
        assert world.reset(state, np.random.default_rng(seed)) == state
        images.append(world.render())
    assert np.abs(images[0].astype(int) - images[1]).sum() > 0


def test_same_seed_same_image(world):
    state = world.task.all_states()[5]
    images = []
    for _ in range(2):
        world.reset(state, np.random.default_rng(7))
        images.append(world.render())
    assert np.array_equal(images[0], images[1])


def test_different_states_look_different(world):
    a, b = world.task.all_states()[:2]
    world.reset(a, np.random.default_rng(0))
    ia = world.render()
    world.reset(b, np.random.default_rng(0))
    assert np.abs(ia.astype(int) - world.render()).sum() > 1000


@pytest.mark.parametrize("size", [128, 256])
def test_larger_images(size):
    with BoxStackingWorld(image_size=size) as w:
        state = w.task.all_states()[42]
        assert w.reset(state, np.random.default_rng(0)) == state
        assert w.render().shape == (size, size, 3)


def test_legal_actions_execute_physically(world):
    rng = np.random.default_rng(1)
    task = world.task
    for state in task.all_states()[::24]:
        for action in task.legal_actions(state):
            world.reset(state, rng)
            assert world.execute(action, rng) == task.apply(state, action)


def test_a_chain_of_moves_without_reset(world):
    rng = np.random.default_rng(2)
    task = world.task
    state = world.reset(task.all_states()[0], rng)
    for _ in range(12):
        legal = task.legal_actions(state)
        action = legal[int(rng.integers(len(legal)))]
        expected = task.apply(state, action)
        state = world.execute(action, rng)
        assert state == expected


def test_illegal_action_raises_and_leaves_world_unchanged(world):
    rng = np.random.default_rng(3)
    state = world.task.parse_state({"stacks": [["red", "green"], [], ["blue", "yellow"]]})
    world.reset(state, rng)
    qpos, image = world.data.qpos.copy(), world.render()
    with pytest.raises(IllegalActionError, match="not the top"):
        world.execute(Move(Cell(0, 0), Cell(0, 1)), rng)
    with pytest.raises(IllegalActionError, match="empty"):
        world.execute(Move(Cell(0, 1), Cell(2, 2)), rng)
    assert np.array_equal(world.data.qpos, qpos)
    assert np.array_equal(world.render(), image)
    assert world.read_state() == state


def test_reset_rejects_invalid_state(world):
    with pytest.raises(InvalidStateError, match="appears twice"):
        world.reset((("red", "red"), ("blue",), ("yellow",)), np.random.default_rng(0))


def test_read_state_detects_a_box_off_the_grid(world):
    world.reset(world.task.all_states()[0], np.random.default_rng(0))
    adr = world._qpos_adr["red"]
    world.data.qpos[adr : adr + 3] = (0.3, 0.3, 0.03)  # between nowhere and nothing
    from services.sim.rendering import mujoco

    mujoco.mj_forward(world.model, world.data)
    with pytest.raises(WorldError, match="red"):
        world.read_state()


def test_image_size_is_validated():
    with pytest.raises(ValueError, match="image size"):
        BoxStackingWorld(image_size=4)
