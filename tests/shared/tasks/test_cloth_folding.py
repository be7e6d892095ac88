import json

import numpy as np
import pytest

from shared.tasks import get_task
from shared.tasks.base import IllegalActionError, InvalidActionError, InvalidStateError
from shared.tasks.cloth_folding import ClothAction, ClothFolding, Pixel

TASK = ClothFolding()
CORNERS = ["top_left", "top_right", "bottom_left", "bottom_right"]


def act(pr, pc, rr, rc, h):
    return ClothAction(Pixel(pr, pc), Pixel(rr, rc), h)


def test_sixteen_states_each_with_four_moves_and_connected():
    states = TASK.all_states()
    assert len(set(states)) == 16
    for s in states:
        assert TASK.parse_state(TASK.state_to_json(s)) == s
        assert TASK.array_to_state(TASK.state_to_array(s)) == s
        successors = {t for _, t in TASK.neighbours(s)}
        assert len(successors) == 4 and all(len(set(s) ^ set(t)) == 1 for t in successors)
    # every state is reachable from the flat cloth (breadth first)
    seen, frontier = {()}, [()]
    while frontier:
        frontier = [t for s in frontier for _, t in TASK.neighbours(s) if t not in seen]
        seen.update(frontier)
    assert seen == set(states)


def test_info_follows_the_interface():
    info = get_task("cloth_folding").info()
    assert info["folds"] == CORNERS
    assert (info["num_states"], info["image_frame"], info["num_transitions"]) == (16, 256, 64)
    assert info["action_fields"] == ["pick.row", "pick.col", "release.row", "release.col", "height"]
    json.dumps(info)


def test_state_is_an_order_free_set():
    a = TASK.parse_state({"folds": ["bottom_right", "top_left"]})
    assert a == TASK.parse_state({"folds": ["top_left", "bottom_right"]})
    assert TASK.state_to_json(a) == {"folds": ["top_left", "bottom_right"]}
    assert TASK.parse_state({"folds": []}) == ()


@pytest.mark.parametrize(
    ("state", "message"),
    [
        ({"folds": ["top_middle"]}, r"state.folds\[0\]: unknown fold 'top_middle'"),
        ({"folds": ["top_left", "top_left"]}, r"state.folds\[1\]: fold 'top_left' appears twice"),
        ({"stacks": [["red"], [], []]}, r"'folds' list \(got keys \['stacks'\]\)"),
        ({"folds": [], "x": 1}, "unknown key 'x'"),
        ({"folds": "top_left"}, "state.folds: expected a list"),
        ({"folds": [3]}, r"state.folds\[0\]: unknown fold 3"),
        ([], "expected an object"),
    ],
)
def test_invalid_states_name_the_field(state, message):
    with pytest.raises(InvalidStateError, match=message):
        TASK.parse_state(state)


GOOD = {"pick": {"row": 48, "col": 48}, "release": {"row": 128, "col": 128}, "height": 0}


@pytest.mark.parametrize(
    ("patch", "message"),
    [
        ({"pick": {"row": 256, "col": 3}}, r"action.pick.row: 256 is out of range 0..255"),
        ({"release": {"row": 3, "col": -1}}, "action.release.col: -1 is out of range"),
        ({"release": {"row": 3.5, "col": 1}}, "action.release.row: expected an integer"),
        ({"height": 2}, r"action.height: expected 0 \(table\) or 1 \(top layer\), got 2"),
        ({"height": True}, "action.height"),
        ({"pick": {"row": 1}}, "action.pick: expected an object with 'row' and 'col'"),
        ({"speed": 1}, "unknown key 'speed'"),
    ],
)
def test_malformed_actions_name_the_field(patch, message):
    with pytest.raises(InvalidActionError, match=message):
        TASK.parse_action({**GOOD, **patch})


def test_action_json_round_trip_and_arrays_hold_every_pixel():
    action = TASK.parse_action({**GOOD, "pick": {"row": 255, "col": 200}})
    assert TASK.parse_action(TASK.action_to_json(action)) == action
    u = TASK.action_to_array(action)
    assert u.dtype == np.int16 and u.tolist() == [255, 200, 128, 128, 0]
    assert TASK.array_to_action(u) == action
    assert TASK.array_to_action(TASK.action_to_array(None)) is None


def test_clicks_match_within_tolerance():
    fold = TASK.moves["fold", "top_left"].action
    assert fold.pick == Pixel(44, 44) and fold.release == Pixel(128, 128)  # corner at 48
    near = act(fold.pick.row + 6, fold.pick.col - 7, 125, 131, 0)  # 9.2 px and 4.2 px off
    assert TASK.apply((), near) == ("top_left",)
    far = act(fold.pick.row + 8, fold.pick.col + 8, 128, 128, 0)  # 11.3 px off
    with pytest.raises(IllegalActionError, match="no fold or unfold matches"):
        TASK.check_action((), far)


def test_rules_name_what_is_wrong():
    fold = TASK.moves["fold", "top_right"].action
    with pytest.raises(IllegalActionError, match="'top_right' is already folded"):
        TASK.check_action(("top_right",), fold)
    unfold = TASK.moves["unfold", "bottom_left"].action
    with pytest.raises(IllegalActionError, match="'bottom_left' is not folded"):
        TASK.check_action((), unfold)
    with pytest.raises(IllegalActionError, match="no fold or unfold"):  # the right place, but h=1
        TASK.check_action((), fold._replace(height=1))
    assert TASK.apply(("bottom_left", "top_right"), unfold) == ("top_right",)


def test_unfold_is_the_fold_undone():
    for corner in CORNERS:
        state = TASK.apply((), TASK.moves["fold", corner].action)
        assert TASK.apply(state, TASK.moves["unfold", corner].action) == ()


def test_moves_are_distinguishable_at_the_tolerance():
    moves = list(TASK.moves.values())
    for i, a in enumerate(moves):
        for b in moves[i + 1 :]:
            if a.action.height != b.action.height:
                continue
            gap = max(
                np.hypot(*np.subtract(a.action.pick, b.action.pick)),
                np.hypot(*np.subtract(a.action.release, b.action.release)),
            )
            assert gap > 2 * TASK.config.tolerance, (a, b)
