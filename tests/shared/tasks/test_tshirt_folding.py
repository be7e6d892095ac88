import itertools
import json

import numpy as np
import pytest

from shared.tasks import get_task
from shared.tasks.base import IllegalActionError, InvalidStateError, optimal_moves
from shared.tasks.folding import ClothAction, Pixel
from shared.tasks.tshirt_folding import FOLDS, TshirtConfig, TshirtFolding

TASK = TshirtFolding()


def test_thirty_two_states_eighty_transitions_and_plans_up_to_eight_moves():
    states = TASK.all_states()
    assert len(set(states)) == 32
    assert sum(len(TASK.legal_actions(s)) for s in states) == 80
    assert max(optimal_moves(TASK, a, b, by_state=True) for a in states for b in states) == 8
    for s in states:
        assert TASK.parse_state(TASK.state_to_json(s)) == s
        assert TASK.array_to_state(TASK.state_to_array(s)) == s
        for _, t in TASK.neighbours(s):
            assert len(set(s) ^ set(t)) == 1
            assert TASK.apply(t, TASK.moves["unfold" if len(t) > len(s) else "fold",
                                            (set(s) ^ set(t)).pop()].action) == s  # fmt: skip


def test_the_rules_of_the_issue():
    flat = ()
    assert len(TASK.legal_actions(flat)) == 5  # every fold
    half = ("bottom_half",)
    assert [TASK.match(a).fold for a in TASK.legal_actions(half)] == ["bottom_half"]
    side = ("left_side",)
    legal = {(TASK.match(a).kind, TASK.match(a).fold) for a in TASK.legal_actions(side)}
    assert legal == {
        ("unfold", "left_side"),
        ("fold", "right_sleeve"),
        ("fold", "right_side"),
        ("fold", "bottom_half"),
    }
    fold = TASK.moves["fold", "left_sleeve"].action
    with pytest.raises(IllegalActionError, match="'left_sleeve' cannot fold while 'left_side'"):
        TASK.apply(side, fold)
    with pytest.raises(IllegalActionError, match="while 'bottom_half' is folded"):
        TASK.apply(("left_sleeve", "bottom_half"), TASK.moves["unfold", "left_sleeve"].action)


def test_a_sleeve_under_the_folded_bottom_half_is_hidden_in_twelve_states_of_five_looks():
    assert TASK.hidden(("left_sleeve", "left_side")) == frozenset()  # its outline shows
    assert TASK.hidden(("left_side", "bottom_half")) == {"left_sleeve"}
    assert TASK.hidden(("left_side", "right_side", "bottom_half")) == set(FOLDS[:2])
    hiding = [s for s in TASK.all_states() if TASK.hidden(s)]
    looks = {tuple(f for f in s if f not in TASK.hidden(s)) for s in hiding}
    assert (len(hiding), len(looks)) == (12, 5)
    cloth = get_task("cloth_folding")
    assert not any(cloth.hidden(s) for s in cloth.all_states())  # a camera sees every fold


def test_the_viewer_is_told_which_folds_hold_each_fold_in_place():
    """info()['locked_by'] is what the viewer disables checkboxes by: it must say exactly
    which moves the rules allow, in every state."""
    locked_by = json.loads(json.dumps(TASK.info()))["locked_by"]
    assert locked_by["bottom_half"] == []
    assert locked_by["left_sleeve"] == ["bottom_half", "left_side"]
    for state in TASK.all_states():
        legal = {TASK.match(a).fold for a in TASK.legal_actions(state)}
        assert legal == {f for f in FOLDS if not set(locked_by[f]) & set(state)}, state


def test_moves_are_told_apart_by_more_than_twice_the_tolerance():
    moves = list(TASK.moves.values())
    assert len(moves) == 10
    for a, b in itertools.combinations(moves, 2):
        if a.action.height != b.action.height:
            continue
        gap = max(
            np.hypot(*np.subtract(a.action.pick, b.action.pick)),
            np.hypot(*np.subtract(a.action.release, b.action.release)),
        )
        assert gap > 2 * TASK.tolerance, (a, b)


def test_a_click_within_tolerance_names_the_move_and_one_beyond_it_none():
    move = TASK.moves["fold", "right_side"]
    pick, release = move.action.pick, move.action.release
    near = ClothAction(Pixel(pick.row + 7, pick.col - 7), release, 0)
    assert TASK.match(near) == move
    far = ClothAction(Pixel(pick.row + 11, pick.col), release, 0)
    assert TASK.match(far) is None
    assert TASK.match(ClothAction(pick, release, 1)) is None  # height is part of the move


def test_fold_lines_keep_every_layer_on_its_own_side():
    c = TASK.config
    assert c.armhole - c.sleeve_length > c.side_line  # a folded sleeve lies inside the strip
    flap_edge = c.armhole - 2 * c.side_width  # a folded side's outer edge, now near the middle
    carried_tip = flap_edge - c.sleeve_length  # the tip of the unfolded sleeve it carries
    assert carried_tip > 0  # it stops short of the middle: of the other side's sleeve and flap
    with pytest.raises(ValueError, match="must not reach the other side's"):
        TshirtConfig(side_width=0.072, sleeve_length=0.055)


def test_info_follows_the_interface():
    info = get_task("tshirt_folding").info()
    assert info["folds"] == list(FOLDS)
    assert (info["num_states"], info["num_transitions"], info["image_frame"]) == (32, 80, 256)
    assert info["tolerance_px"] == TASK.tolerance
    assert {(m["kind"], m["fold"]) for m in info["moves"]} == {
        (k, f) for k in ("fold", "unfold") for f in FOLDS
    }
    for m in info["moves"]:
        assert TASK.parse_action(m["action"]) == TASK.moves[m["kind"], m["fold"]].action
    json.dumps(info)


@pytest.mark.parametrize(
    ("state", "message"),
    [
        ({"folds": ["left_cuff"]}, r"state.folds\[0\]: unknown fold 'left_cuff'"),
        ({"folds": ["left_side", "left_side"]}, r"state.folds\[1\]: fold 'left_side' appears"),
        ({"folds": "bottom_half"}, "state.folds: expected a list"),
        ({"stacks": []}, "'folds' list"),
    ],
)
def test_invalid_states_are_named(state, message):
    with pytest.raises(InvalidStateError, match=message):
        TASK.parse_state(state)


def test_views_are_what_a_camera_above_tells_apart():
    """32 states, 25 views (interface.md, "Views"): with the bottom half folded, a folded
    side hides its sleeve, folded or not; every other part shows."""
    shirt = get_task("tshirt_folding")
    assert shirt.num_views() == 25 and shirt.info()["num_views"] == 25
    hidden = shirt.parse_state({"folds": ["left_sleeve", "left_side", "bottom_half"]})
    open_sleeve = shirt.parse_state({"folds": ["left_side", "bottom_half"]})
    assert shirt.view(hidden) == shirt.view(open_sleeve)
    shown = shirt.parse_state({"folds": ["left_sleeve", "left_side"]})
    assert shirt.view(shown) != shirt.view(shirt.parse_state({"folds": ["left_side"]}))
    for name, states in (("box_stacking", 288), ("cloth_folding", 16)):
        task = get_task(name)  # nothing hides: every state is its own view
        assert task.num_views() == states == task.info()["num_views"]
        assert all(task.view(s) == s for s in task.all_states())
