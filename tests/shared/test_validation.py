"""Field checks shared by the gateway and the services."""

import pytest

from shared.tasks import get_task
from shared.validation import FieldError, parse_state

TASK = get_task("box_stacking")
STATE = {"stacks": [["red"], ["green", "blue"], ["yellow"]]}


def test_states_parse_and_refuse_unknown_keys_by_name():
    assert parse_state(TASK, "start.state", STATE) == TASK.parse_state(STATE)
    with pytest.raises(FieldError, match="unknown key 'x'") as info:
        parse_state(TASK, "start.state", {**STATE, "x": 1})
    assert info.value.field == "start.state.x"


def test_invalid_states_name_their_field():
    with pytest.raises(FieldError) as info:
        parse_state(TASK, "goal.state", {"stacks": [["red", "red"], [], []]})
    assert info.value.field == "goal.state"
