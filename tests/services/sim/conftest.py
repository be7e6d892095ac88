import pytest

from services.sim.box_stacking.world import BoxStackingWorld


@pytest.fixture(scope="session")
def world():
    w = BoxStackingWorld(image_size=64)
    yield w
    w.close()
