import numpy as np
import pytest

from shared.tasks import get_task
from shared.tasks.base import IllegalActionError, InvalidActionError, InvalidStateError, TaskError
from shared.tasks.box_stacking import BoxStacking, Cell, Move

TASK = BoxStacking()
S = {"stacks": [["red", "green"], [], ["blue", "yellow"]]}


def move(pr, pc, rr, rc):
    return Move(Cell(pr, pc), Cell(rr, rc))


def test_exactly_288_distinct_valid_states():
    states = TASK.all_states()
    assert len(states) == 288
    assert len(set(states)) == 288
    for s in states:
        assert TASK.parse_state(TASK.state_to_json(s)) == s
        assert sorted(b for col in s for b in col) == sorted(TASK.config.boxes)


def test_info_matches_interface():
    info = get_task("box_stacking").info()
    assert info["boxes"] == ["red", "green", "blue", "yellow"]
    assert (info["columns"], info["levels"], info["num_states"]) == (3, 3, 288)


def test_unknown_task_names_the_known_ones():
    with pytest.raises(TaskError, match="box_stacking"):
        get_task("cloth")


def test_legal_actions_from_a_state():
    s = TASK.parse_state(S)
    assert set(TASK.legal_actions(s)) == {
        move(1, 0, 0, 1),
        move(1, 0, 2, 2),
        move(1, 2, 0, 1),
        move(1, 2, 2, 0),
    }


def test_apply_moves_the_top_box():
    s = TASK.parse_state(S)
    assert TASK.apply(s, move(1, 2, 0, 1)) == (("red", "green"), ("yellow",), ("blue",))


@pytest.mark.parametrize(
    ("action", "rule"),
    [
        (move(1, 0, 2, 0), "same column"),
        (move(0, 1, 0, 0), "empty"),
        (move(0, 0, 0, 1), "not the top"),
        (move(1, 0, 0, 2), "not the free cell"),
        (move(1, 0, 1, 1), "not the free cell"),
    ],
)
def test_illegal_actions_name_the_rule(action, rule):
    with pytest.raises(IllegalActionError, match=rule):
        TASK.apply(TASK.parse_state(S), action)


def test_release_on_a_full_column_is_illegal():
    s = TASK.parse_state({"stacks": [["red", "green", "blue"], ["yellow"], []]})
    with pytest.raises(IllegalActionError, match="full"):
        TASK.apply(s, move(0, 1, 3 - 1, 0))


def test_transition_graph_is_symmetric_and_counted():
    edges = {(s, t) for s in TASK.all_states() for _, t in TASK.neighbours(s)}
    assert all((t, s) in edges for s, t in edges)
    assert len(edges) == TASK.info()["num_transitions"]


@pytest.mark.parametrize(
    ("state", "message"),
    [
        ({"stacks": [["red", "green", "blue", "yellow"], [], []]}, "at most 3"),
        ({"stacks": [["red", "red"], ["blue"], ["yellow"]]}, "appears twice"),
        ({"stacks": [["red", "purple"], ["blue"], ["yellow"]]}, "unknown box id 'purple'"),
        ({"stacks": [["red"], ["blue"], ["yellow"]]}, "missing boxes \\['green'\\]"),
        ({"stacks": [["red", "green"], ["blue", "yellow"]]}, "expected 3 columns"),
        ({"stacks": [["red"], ["green"], ["blue"], ["yellow"]]}, "expected 3 columns"),
        ({"stacks": "red"}, "list of columns"),
        ({"stacks": [["red", 3], ["green"], ["blue", "yellow"]]}, "unknown box id 3"),
        ({"columns": []}, "'stacks'"),
        ([], "'stacks'"),
        ({"stacks": [["red", "green"], ["blue"], ["yellow"]], "x": 1}, "unknown key 'x'"),
        ({"stacks": [["red", "green"], ["blue"], ["yellow"]], "folds": []}, "unknown key 'folds'"),
    ],
)
def test_invalid_states_are_named(state, message):
    with pytest.raises(InvalidStateError, match=message):
        TASK.parse_state(state)


@pytest.mark.parametrize(
    ("action", "message"),
    [
        ({"pick": {"row": 0, "col": 3}, "release": {"row": 0, "col": 0}}, "pick.col: 3"),
        ({"pick": {"row": 0, "col": 0}, "release": {"row": -1, "col": 1}}, "release.row: -1"),
        ({"pick": {"row": "0", "col": 0}, "release": {"row": 0, "col": 1}}, "pick.row"),
        ({"pick": {"row": True, "col": 0}, "release": {"row": 0, "col": 1}}, "pick.row"),
        ({"pick": {"row": 0, "col": 0}}, "release"),
    ],
)
def test_malformed_actions_are_named(action, message):
    with pytest.raises(InvalidActionError, match=message):
        TASK.parse_action(action)


def test_action_json_round_trip():
    a = move(1, 0, 2, 2)
    assert TASK.parse_action(TASK.action_to_json(a)) == a


def test_array_codecs_round_trip():
    for s in TASK.all_states()[::17]:
        assert TASK.array_to_state(TASK.state_to_array(s)) == s
    a = move(1, 2, 0, 1)
    assert TASK.array_to_action(TASK.action_to_array(a)) == a
    assert TASK.array_to_action(TASK.action_to_array(None)) is None
    assert TASK.action_to_array(None).tolist() == [-1, -1, -1, -1]


def test_sample_state_is_seeded():
    a = [TASK.sample_state(np.random.default_rng(3)) for _ in range(2)]
    assert a[0] == a[1]
