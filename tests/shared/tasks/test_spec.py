import numpy as np
import pytest

from shared.tasks import get_task, task_names
from shared.tasks.spec import ArraySpec, SpecError, TaskSpec


def pixels(dtype="int16"):
    return ArraySpec(dtype, (3,), ("row", "col", "h"), (256, 256, 2), nullable=True,
                     pixels={"row": "row", "col": "col"}, frame=256)  # fmt: skip


def test_dtype_too_small_for_the_range_is_refused():
    with pytest.raises(SpecError, match=r"int8 holds -128\.\.127, the values need -1\.\.255"):
        pixels("int8")
    assert pixels("int16").counts == (256, 256, 2)


@pytest.mark.parametrize(
    ("kw", "message"),
    [
        ({"names": ("a",)}, "1 names and 2 counts for 2 elements"),
        ({"counts": (0, 3)}, "at least 1"),
        ({"dtype": "float32"}, "not an integer dtype"),
        ({"pixels": {"a": "row"}}, "frame"),
        ({"pixels": {"z": "row"}, "frame": 8}, "pixels"),
    ],
)
def test_malformed_specs(kw, message):
    args = {"dtype": "int8", "shape": (2,), "names": ("a", "b"), "counts": (3, 3), **kw}
    with pytest.raises(SpecError, match=message):
        ArraySpec(**args)


def test_validate_names_the_field_and_element():
    spec = pixels()
    spec.validate(np.array([[0, 255, 1], [-1, -1, -1]], np.int16), "u")  # a row of NULL is fine
    with pytest.raises(SpecError, match=r"u\[1\]: col = 256 is out of range 0..255"):
        spec.validate(np.array([[0, 0, 0], [3, 256, 1]], np.int16), "u")
    with pytest.raises(SpecError, match=r"u\[0\]: row = -1"):
        spec.validate(np.array([[-1, 4, 1]], np.int16), "u")  # partly NULL is not NULL
    with pytest.raises(SpecError, match="expected int16 of shape"):
        spec.validate(np.zeros((2, 3), np.int8), "u")


def test_every_registered_task_spec_round_trips_through_json():
    for name in task_names():
        spec = get_task(name).spec
        assert TaskSpec.from_json(spec.to_json()) == spec


def test_task_codecs_produce_what_the_spec_declares():
    for name in task_names():
        task = get_task(name)
        states = task.all_states()
        arrays = np.stack([task.state_to_array(s) for s in states])
        task.spec.state.validate(arrays, "state")
        actions = [a for s in states[:5] for a in task.legal_actions(s)]
        u = np.stack([task.action_to_array(a) for a in [*actions, None]])
        task.spec.action.validate(u, "u")
        assert [task.array_to_action(row) for row in u] == [*actions, None]


def test_spec_json_errors_name_the_part():
    with pytest.raises(SpecError, match=r"spec\.action: missing 'dtype'"):
        TaskSpec.from_json({"task": "x", "action": {"shape": [1]}, "state": None})
    with pytest.raises(SpecError, match="'task'"):
        TaskSpec.from_json([])
