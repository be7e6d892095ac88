import numpy as np
import pytest

from services.sim.datagen import GenerateConfig, generate
from services.sim.state_reader import load_reader, read_states, train_reader
from shared.dataset import load_dataset


def test_train_save_load_read(tmp_path):
    generate(
        GenerateConfig(pairs=24, seed=4, image_size=32, workers=1), tmp_path / "d", progress=False
    )
    data = load_dataset(tmp_path / "d")
    meta = train_reader(data, tmp_path / "r", epochs=1, progress=False)
    assert meta["model"]["cells"] == 9 and meta["model"]["values"] == 5
    reader = load_reader(tmp_path / "r")
    reads = read_states(reader, data.image1)
    assert reads.shape == (24, 3, 3) and reads.dtype == np.int8
    assert reads.min() >= -1 and reads.max() <= 3
    again = read_states(load_reader(tmp_path / "r"), data.image1)
    assert np.array_equal(reads, again)


def test_load_reader_error(tmp_path):
    with pytest.raises(ValueError, match="not a state reader"):
        load_reader(tmp_path)
