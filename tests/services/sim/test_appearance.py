"""The appearance wrapper and its modder, on real MuJoCo worlds."""

import mujoco
import numpy as np
import pytest

from services.sim.appearance import AppearanceWorld, SceneModder, appearance_rng, post_process
from services.sim.cloth_folding.world import ClothFoldingWorld
from services.sim.rendering import OffscreenCamera
from shared.appearance import ImageSample
from shared.tasks import get_task
from shared.tasks.base import World

STATE = {"stacks": [["red"], ["green", "blue"], ["yellow"]]}


def box_state(world):
    return world.task.parse_state(STATE)


def model_arrays(world):
    m, d = world.model, world.data
    return [
        np.array(a, copy=True)
        for a in (
            m.light_dir,
            m.light_diffuse,
            m.light_ambient,
            m.cam_pos,
            m.cam_quat,
            m.mat_rgba,
            m.geom_rgba,
            m.mat_texrepeat,
            m.tex_data,
            m.vis.headlight.ambient,
            m.vis.headlight.diffuse,
            d.cam_xpos,
            d.cam_xmat,
            d.light_xdir,
        )
    ]


def test_clean_is_the_world_byte_for_byte(world):
    state = box_state(world)
    bare_rng, wrapped_rng = np.random.default_rng(4), np.random.default_rng(4)
    world.reset(state, bare_rng)
    bare = [world.render(), world.render()]
    wrapped = AppearanceWorld(world, "clean")
    wrapped.reset(state, wrapped_rng)
    images = [wrapped.render(), wrapped.render()]
    assert all(np.array_equal(a, b) for a, b in zip(bare, images, strict=True))
    assert bare_rng.bit_generator.state == wrapped_rng.bit_generator.state
    assert wrapped.episode_sample is None


def test_camera_changes_the_look_only(world):
    """Same physics draws and poses as clean; the model is as it was after every render."""
    state = box_state(world)
    clean_rng, camera_rng = np.random.default_rng(5), np.random.default_rng(5)
    world.reset(state, clean_rng)
    clean_image, clean_qpos = world.render(), world.data.qpos.copy()
    before = model_arrays(world)
    camera = AppearanceWorld(world, "camera")
    camera.reset(state, camera_rng)
    assert np.array_equal(world.data.qpos, clean_qpos)
    assert clean_rng.bit_generator.state == camera_rng.bit_generator.state
    image = camera.render()
    assert image.shape == clean_image.shape and image.dtype == np.uint8
    assert np.abs(image.astype(int) - clean_image).mean() > 2
    after = model_arrays(world)
    assert all(np.array_equal(a, b) for a, b in zip(before, after, strict=True))
    assert np.array_equal(world.render(), clean_image)  # the GPU's table texture is back too


def test_a_no_action_pair_keeps_its_episode_draws(world):
    camera = AppearanceWorld(world, "camera")
    rng = np.random.default_rng(6)
    camera.reset(box_state(world), rng)
    episode = camera.episode_sample
    first = camera.render()
    camera.perturb(rng)
    assert camera.episode_sample is episode  # a perturbation is the same scene
    second = camera.render()
    assert not np.array_equal(first, second)
    camera.reset(box_state(world), rng)
    assert camera.episode_sample != episode  # a reset is a new episode


def test_same_seed_same_bytes_and_another_seed_another_look(world):
    def images(seed):
        camera = AppearanceWorld(world, "camera")
        rng = np.random.default_rng(seed)
        camera.reset(box_state(world), rng)
        return camera.render(), camera.render(), camera.episode_sample

    a, b = images(9), images(9)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) and a[2] == b[2]
    assert images(10)[2] != a[2]


def test_the_appearance_stream_reads_the_rng_without_drawing():
    rng = np.random.default_rng([3, 4, 0])
    state = rng.bit_generator.state
    first = appearance_rng(rng).random()
    assert rng.bit_generator.state == state
    assert appearance_rng(rng).random() == first
    rng.random()
    assert appearance_rng(rng).random() != first


def test_shifted_moves_the_image_further_than_camera(world):
    state = box_state(world)
    world.reset(state, np.random.default_rng(0))
    clean = world.render().astype(int)
    distance = {}
    for level in ("camera", "shifted"):
        wrapped = AppearanceWorld(world, level)
        total = 0.0
        for seed in range(6):
            wrapped.reset(state, np.random.default_rng(seed))
            total += np.abs(wrapped.render().astype(int) - clean).mean()
        distance[level] = total
    assert distance["shifted"] > 1.3 * distance["camera"]


def test_post_processing_applies_gains_noise_and_jpeg():
    image = np.full((32, 32, 3), 128, np.uint8)
    same = post_process(image, ImageSample((1.0, 1.0, 1.0), 0.0, 0, 95))
    assert same.dtype == np.uint8 and same.shape == image.shape
    assert np.abs(same.astype(int) - 128).max() <= 1
    warm = post_process(image, ImageSample((1.1, 1.0, 0.9), 0.0, 0, 95)).mean(axis=(0, 1))
    assert warm[0] > 138 and warm[2] < 118
    noisy = post_process(image, ImageSample((1.0, 1.0, 1.0), 8 / 255, 1, 95)).astype(int)
    assert 3 < noisy.std() < 12


def test_levels_switch_on_a_served_world(world):
    wrapped = AppearanceWorld(world, "camera")
    wrapped.use("clean")
    state = box_state(world)
    wrapped.reset(state, np.random.default_rng(2))
    world_image = wrapped.world.render()
    assert np.array_equal(wrapped.render(), world_image)
    with pytest.raises(ValueError, match="unknown appearance level 'fog'"):
        wrapped.use("fog")


def test_delegates_what_it_does_not_change(world):
    wrapped = AppearanceWorld(world, "camera")
    assert wrapped.task is world.task and wrapped.image_size == world.image_size
    assert wrapped.episode_length == world.episode_length and wrapped.settles == world.settles
    assert wrapped.cell_pixel(0, 0) == world.cell_pixel(0, 0)  # not a World method: delegated


def test_cloth_world_with_the_same_modder():
    with ClothFoldingWorld(image_size=32, lattice=5) as cloth:
        flat = cloth.task.parse_state({"folds": []})
        cloth.reset(flat, np.random.default_rng(0))
        clean = cloth.render()
        camera = AppearanceWorld(cloth, "camera")
        camera.reset(flat, np.random.default_rng(0))
        assert np.abs(camera.render().astype(int) - clean).mean() > 2
        assert np.array_equal(cloth.render(), clean)


class TinyWorld(World):
    """Any world with a camera, a light, a headlight and a plain table geom (no material)."""

    def __init__(self) -> None:
        self.task = get_task("box_stacking")
        self.image_size = 32
        self.model = mujoco.MjModel.from_xml_string(
            """<mujoco><visual><headlight ambient=".4 .4 .4" diffuse=".3 .3 .3"/></visual>
            <worldbody><light name="sun" directional="true" dir="0 0 -1"/>
            <geom name="table" type="box" size="1 1 .01" rgba=".7 .6 .5 1"/>
            <geom type="sphere" size=".05" pos="0 0 .06" rgba=".2 .3 .9 1"/>
            <camera name="top" pos="0 0 .5"/></worldbody></mujoco>"""
        )
        self.data = mujoco.MjData(self.model)
        mujoco.mj_forward(self.model, self.data)
        self.camera = OffscreenCamera(self.model, "top", 32)

    def reset(self, state, rng):
        return state

    def render(self):
        return self.camera.render(self.data)

    def read_state(self):
        return None

    def execute(self, action, rng):
        return None

    def close(self):
        self.camera.close()


def test_a_world_without_table_material_gets_its_colour_varied():
    with TinyWorld() as tiny:
        clean = tiny.render()
        rgba = tiny.model.geom_rgba.copy()
        camera = AppearanceWorld(tiny, "camera")
        camera.reset(None, np.random.default_rng(1))
        assert not np.array_equal(camera.render(), clean)
        assert np.array_equal(tiny.model.geom_rgba, rgba)


def test_a_world_without_mujoco_is_refused_by_name():
    class Blind(TinyWorld):
        def __init__(self) -> None:
            self.task = get_task("box_stacking")

    with pytest.raises(TypeError, match=r"Blind: appearance needs a MjModel as \.model"):
        SceneModder(Blind())


def test_a_head_camera_moves_before_every_look_and_the_light_stays(world):
    """`Observer(moving=True)`: the camera's pose drawn anew for every image of an episode,
    the light and the table as the episode drew them."""
    from services.sim.workcell import Observer

    world = AppearanceWorld(world, "camera")
    world.reset(box_state(world), np.random.default_rng(4))
    light = world._episode.light_gain
    observer = Observer(world, moving=True)
    poses = []
    for _ in range(3):
        observer.see()  # registered, as every image a model is given
        poses.append(world.pinhole().position.copy())
        assert world._episode.light_gain == light
    assert np.linalg.norm(poses[0] - poses[1]) > 1e-4 and np.linalg.norm(poses[1] - poses[2]) > 1e-4
    still = Observer(world)
    pose = world.pinhole().position.copy()
    still.see()
    assert np.array_equal(world.pinhole().position, pose)  # a cell's camera stays
