"""The sim service's render handler: the model's training appearance unless a request names one."""

from dataclasses import replace

import numpy as np
import pytest

from services.runtime import ModelInfo, ServiceContext
from services.sim import service as sim_service
from services.sim.worlds import make_world
from services.stack import free_port
from shared.bus import BusConfig, close_quietly, open_session
from shared.messages import RenderReply, RenderRequest, pack, unpack
from shared.settings import SHIPPED_MODEL, Settings
from shared.validation import FieldError

STATE = {"stacks": [["red"], ["green", "blue"], ["yellow"]]}


@pytest.fixture(scope="module")
def render():
    """The render handler of a sim serving the shipped model as if trained on camera data."""
    session = open_session(BusConfig(mode="router", listen=[f"tcp/127.0.0.1:{free_port()}"]))
    model = replace(ModelInfo.read(SHIPPED_MODEL), appearance="camera")
    handlers = sim_service.setup(ServiceContext("sim", "x", model, session, Settings()))

    def call(**fields) -> np.ndarray:
        request = RenderRequest(task="box_stacking", states=[STATE], seed=3, **fields)
        return unpack(pack(handlers["render"](pack(request))), RenderReply).images.numpy()[0]

    yield call
    close_quietly(session)


def test_render_defaults_to_the_training_appearance(render):
    with make_world("box_stacking", 64) as world:
        world.reset(world.task.parse_state(STATE), np.random.default_rng(3))
        clean = world.render()
    assert np.array_equal(render(appearance="clean"), clean)
    assert np.array_equal(render(), render(appearance="camera"))  # the model's, seeded
    assert not np.array_equal(render(), clean)
    assert not np.array_equal(render(appearance="shifted"), render())


def test_an_unknown_level_names_the_field(render):
    with pytest.raises(FieldError, match="appearance: unknown level 'fog'") as info:
        render(appearance="fog")
    assert info.value.field == "appearance"
