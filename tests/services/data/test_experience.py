import numpy as np
import pytest

from services.data.experience import ExperienceError, ExperienceLog, Recorder
from shared import dataset as ds
from shared.dataset import load_dataset
from shared.tasks import get_task
from shared.tasks.spec import TaskSpec

TASK = get_task("box_stacking")


def tuples(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    states = [TASK.sample_state(rng) for _ in range(n)]
    image = rng.integers(0, 255, (n, 16, 16, 3), dtype=np.uint8)
    u = np.stack([TASK.action_to_array(None)] * n)
    s = np.stack([TASK.state_to_array(x) for x in states])
    return image, image[::-1].copy(), u, s, s


def test_appends_read_back_as_one_dataset(tmp_path):
    log = ExperienceLog(tmp_path / "exp", TASK.spec, 16)
    assert log.append(*tuples(3)) == 3
    assert ExperienceLog(tmp_path / "exp", TASK.spec, 16).append(*tuples(2, seed=1)) == 5
    data = load_dataset(tmp_path / "exp")
    assert len(data) == 5 and data.task == "box_stacking" and not data.a.any()
    assert np.array_equal(data.image1[:3], tuples(3)[0])


def test_a_folder_of_another_spec_or_size_is_refused(tmp_path):
    ExperienceLog(tmp_path / "exp", TASK.spec, 16).append(*tuples(1))
    with pytest.raises(ExperienceError, match="another spec"):
        ExperienceLog(tmp_path / "exp", TASK.spec, 32)
    stateless = TaskSpec(TASK.spec.task, TASK.spec.action, None)
    with pytest.raises(ExperienceError, match="another spec"):
        ExperienceLog(tmp_path / "exp", stateless, 16)
    with pytest.raises(ExperienceError, match="image1"):
        ExperienceLog(tmp_path / "exp", TASK.spec, 16).append(
            np.zeros((1, 8, 8, 3), np.uint8), *tuples(1)[1:]
        )


def test_a_training_set_is_never_appended_to(tmp_path):
    log = ExperienceLog(tmp_path / "exp", TASK.spec, 16)
    log.append(*tuples(1))
    manifest = (tmp_path / "exp" / "manifest.json").read_text()
    training = manifest.replace('"experience"', '"not_experience"')
    (tmp_path / "exp" / "manifest.json").write_text(training)
    with pytest.raises(ExperienceError, match="not an experience folder"):
        ExperienceLog(tmp_path / "exp", TASK.spec, 16)


def test_an_append_killed_mid_write_leaves_what_was_recorded(tmp_path, monkeypatch):
    log = ExperienceLog(tmp_path / "exp", TASK.spec, 16)
    log.append(*tuples(2))
    before = (tmp_path / "exp" / "manifest.json").read_text()

    def dies(path, arrays, spec):
        path.write_bytes(b"half a shard")
        raise KeyboardInterrupt

    monkeypatch.setattr(ds, "write_shard", dies)
    with pytest.raises(KeyboardInterrupt):
        log.append(*tuples(4, seed=2))
    monkeypatch.undo()
    assert (tmp_path / "exp" / "manifest.json").read_text() == before
    assert len(load_dataset(tmp_path / "exp")) == 2  # readable, every shard verified
    assert log.append(*tuples(1, seed=3)) == 3


def test_recorder_writes_in_batches_and_on_flush(tmp_path):
    log = ExperienceLog(tmp_path / "exp", TASK.spec, 16)
    record = Recorder(log, TASK, batch=2)
    image, _, _, _, _ = tuples(3)
    state = TASK.sample_state(np.random.default_rng(0))
    move, after = TASK.neighbours(state)[0]
    record(image[0], move, image[1], state, after)
    assert log.count() == 0
    record(image[1], None, image[2], after, after)
    assert log.count() == 2
    record(image[2], None, image[2], after, after)
    record.flush()
    data = load_dataset(tmp_path / "exp")
    assert data.a.tolist() == [1, 0, 0] and record.recorded == 3
    assert TASK.array_to_action(data.u[0]) == move
    assert TASK.array_to_state(data.state2[0]) == after
