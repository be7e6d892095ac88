"""Tasks defined by their data: task.json declarations and the codec-only DataTask."""

import numpy as np
import pytest

from shared.tasks import declare_task, get_task, has_simulator, known_tasks
from shared.tasks.base import InvalidActionError, InvalidStateError, TaskError
from shared.tasks.declared import DataTask, DeclarationError, TaskDeclaration
from shared.tasks.spec import TaskSpec

TASK = {
    "name": "towel",
    "image_size": 64,
    "frame": 256,
    "action": [
        {"name": "pick.row", "range": [0, 255], "pixel": "row"},
        {"name": "pick.col", "range": [0, 255], "pixel": "col"},
        {"name": "height", "categories": ["table", "top"]},
        {"name": "turn", "range": [-2, 2]},
        {"name": "force", "float": [0.0, 5.0], "levels": 11},
    ],
    "settings": {"d_m": 13.5, "w_eps": 0.8, "min_samples": 6},
}
ACTION = {"pick": {"row": 3, "col": 250}, "height": "top", "turn": -2, "force": 2.5}


def test_declaration_becomes_a_spec_and_back():
    declaration = TaskDeclaration.from_json(TASK)
    action = declaration.spec.action
    assert declaration.spec.state is None and declaration.image_size == 64
    assert action.counts == (256, 256, 2, 5, 11) and action.dtype == "int16"
    assert action.pixels == {"pick.row": "row", "pick.col": "col"} and action.frame == 256
    assert TaskDeclaration.from_json(declaration.to_json()) == declaration
    assert TaskSpec.from_json(declaration.spec.to_json()) == declaration.spec
    assert declaration.to_json()["action"][3] == {"name": "turn", "range": [-2, 2]}


def test_small_ranges_store_as_int8():
    task = {**TASK, "action": [{"name": "cell", "range": [0, 8]}]}
    assert TaskDeclaration.from_json(task).spec.action.dtype == "int8"


def test_actions_are_the_declared_fields_nested_by_their_dots():
    task = DataTask(TaskDeclaration.from_json(TASK).spec)
    action = task.parse_action(ACTION)
    assert action == (3, 250, 1, 0, 5)
    assert task.action_to_json(action) == ACTION
    array = task.action_to_array(action)
    assert array.dtype == np.int16 and task.array_to_action(array) == action
    assert task.array_to_action(task.action_to_array(None)) is None
    assert task.parse_action({**ACTION, "force": 2.74})[4] == 5  # the nearest level


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"pick": {"row": 3}}, r"pick\.col: missing"),
        ({"pick": {"row": 3, "col": 256}}, r"pick\.col: 256 is out of range 0\.\.255"),
        ({"pick": {"row": 3.5, "col": 1}}, r"pick\.row: expected an integer"),
        ({"pick": 7}, r"pick: expected an object with 'row'"),
        ({"height": "floor"}, r"height: expected one of \['table', 'top'\]"),
        ({"turn": 3}, r"turn: 3 is out of range -2\.\.2"),
        ({"force": 5.5}, r"force: 5\.5 is out of range 0\.0\.\.5\.0"),
        ({"force": float("nan")}, r"force: nan is out of range"),
        ({"speed": 1}, r"speed: unknown field"),
        ({"pick": {"row": 3, "col": 1, "z": 0}}, r"pick\.z: unknown field"),
    ],
)
def test_bad_actions_name_the_field(change, message):
    task = DataTask(TaskDeclaration.from_json(TASK).spec)
    with pytest.raises(InvalidActionError, match=message):
        task.parse_action({**ACTION, **change})


def test_a_data_task_has_no_states_rules_or_world():
    task = DataTask(TaskDeclaration.from_json(TASK).spec)
    with pytest.raises(InvalidStateError, match="'towel' is defined by its data: it has no states"):
        task.parse_state({"folds": []})
    with pytest.raises(NotImplementedError, match="no rules"):
        task.legal_actions(None)
    assert task.info()["capabilities"] == {"states": False, "rules": False, "world": False}
    assert task.info()["action_format"]["pick"]["row"] == "0..255 (row pixel of a 256 px frame)"


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"name": "no spaces"}, "name: 1-64 letters"),
        ({"image_size": 100}, "image_size: 100 is not a power of two"),
        ({"image_size": 8}, "image_size: an integer from 16"),
        ({"colour": 1}, "unknown key 'colour'"),
        ({"action": []}, "action: expected a non-empty list"),
        ({"action": [{"name": "a", "range": [0, 1]}, {"name": "a", "range": [0, 1]}]},
         "'a' declared twice"),
        ({"action": [{"name": "a", "range": [0, 1]}, {"name": "a.b", "range": [0, 1]}]},
         "'a' is a field and a group of 'a.b'"),
        ({"action": [{"name": "a", "range": [0, 1], "categories": ["x"]}]},
         r"action\[0\] \(a\): give exactly one of range, categories, float"),
        ({"action": [{"name": "a", "categories": ["x", "x"]}]}, "distinct non-empty"),
        ({"action": [{"name": "a", "float": [1.0, 1.0]}]}, "low < high"),
        ({"action": [{"name": "a", "range": [0, 9], "pixel": "row"}], "frame": None},
         "needs the task's 'frame'"),
        ({"action": [{"name": "a", "range": [0, 9], "pixel": "depth"}]}, "'row' or 'col'"),
        ({"settings": {"d_m": -1}}, r"settings\.d_m: must be positive"),
        ({"settings": {"min_samples": 2.5}}, r"settings\.min_samples: expected an integer"),
        ({"settings": {"lr": 1}}, "settings: unknown key 'lr'"),
        ({"undo": [["pick.row", "nope"]]}, r"spec\.undo: \['nope'\] are not action elements"),
        ({"undo": [["pick.row", "pick.col", "turn"]]}, "pairs of distinct action elements"),
        ({"undo": "pick.row"}, r"undo: expected a list of \[field, field\] pairs"),
    ],
)  # fmt: skip
def test_bad_declarations_name_the_key(change, message):
    with pytest.raises(DeclarationError, match=message):
        TaskDeclaration.from_json({**TASK, **change})


def test_declared_tasks_join_the_registry():
    spec = TaskDeclaration.from_json({**TASK, "name": "towel_registry"}).spec
    with pytest.raises(TaskError, match="unknown task 'towel_registry'"):
        get_task("towel_registry")
    task = declare_task(spec)
    assert get_task("towel_registry") is task and "towel_registry" in known_tasks()
    assert declare_task(spec) is task  # the same spec again is fine
    assert not has_simulator("towel_registry") and has_simulator("cloth_folding")
    other = TaskDeclaration.from_json(
        {**TASK, "name": "towel_registry", "action": TASK["action"][:2]}
    )
    with pytest.raises(TaskError, match="already declared with another spec"):
        declare_task(other.spec)
    # A built-in task's spec gives the built-in task, rules and all.
    assert declare_task(get_task("cloth_folding").spec) is get_task("cloth_folding")


def test_a_declared_undo_survives_json_and_export():
    task = {**TASK, "undo": [["pick.row", "pick.col"]]}
    declaration = TaskDeclaration.from_json(task)
    assert declaration.spec.undo == (("pick.row", "pick.col"),)
    assert TaskDeclaration.from_json(declaration.to_json()).spec.undo == declaration.spec.undo
    assert TaskSpec.from_json(declaration.spec.to_json()).undo == declaration.spec.undo
    assert TaskDeclaration.of_spec(declaration.spec, 64).spec.undo == declaration.spec.undo
    assert "undo" not in TaskDeclaration.from_json(TASK).to_json()  # none declared, none written
