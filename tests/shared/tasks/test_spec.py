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
        assert TaskSpec.from_json(spec.to_json()).undo == spec.undo  # equality ignores it


def test_a_declared_undo_is_true_by_the_rules():
    """Every legal move from every state, then its undoing action, gives the state back."""
    declared = [name for name in task_names() if get_task(name).spec.undo]
    assert "box_stacking" in declared
    for name in declared:
        task = get_task(name)
        for state in task.all_states():
            for action in task.legal_actions(state):
                u = task.action_to_array(action)[None]
                undo = task.array_to_action(task.spec.undone(u)[0])
                assert task.apply(task.apply(state, action), undo) == state


def test_undo_swaps_elements_and_is_not_part_of_equality():
    spec = get_task("box_stacking").spec
    u = np.array([[0, 1, 2, 0], [-1, -1, -1, -1]], np.int8)
    assert spec.undone(u).tolist() == [[2, 0, 0, 1], [-1, -1, -1, -1]]
    assert u.tolist()[0] == [0, 1, 2, 0]  # a copy, not in place
    bare = TaskSpec(spec.task, spec.action, spec.state)
    assert bare == spec and not bare.undo  # data recorded before the declaration still matches
    with pytest.raises(SpecError, match=r"spec\.undo: \['x'\] are not action elements"):
        TaskSpec(spec.task, spec.action, None, (("pick.row", "x"),))
    with pytest.raises(SpecError, match="each named once"):
        TaskSpec(spec.task, spec.action, None, (("pick.row", "release.row"),) * 2)
    with pytest.raises(SpecError, match="list of"):
        TaskSpec.from_json({**spec.to_json(), "undo": "pick.row"})


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


def test_data_recorded_before_a_builtin_task_declared_undo_gets_it():
    from shared.dataset import manifest_spec

    spec = get_task("box_stacking").spec
    old = {k: v for k, v in spec.to_json().items() if k != "undo"}
    assert manifest_spec({"task": "box_stacking", "spec": old}).undo == spec.undo
    declared = {**old, "task": "towel_like"}  # a data-only task keeps what its data declare
    assert manifest_spec({"task": "towel_like", "spec": declared}).undo == ()
