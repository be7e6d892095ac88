import numpy as np
import pytest

from shared.tasks import get_task
from shared.tasks.base import (
    IllegalActionError,
    InvalidActionError,
    InvalidStateError,
    optimal_moves,
)
from shared.tasks.rope_box import KINDS, Cell, RopeBoxAction

TASK = get_task("rope_box")


def state(green, orange, rope=None):
    boxes = {
        box: {"row": cell[0], "col": cell[1]}
        for box, cell in (("green", green), ("orange", orange))
    }
    return TASK.parse_state({"boxes": boxes, "rope": rope})


def bent(row, col, turn):
    return {"pillar": {"row": row, "col": col}, "turn": turn}


def push(pick, release):
    return RopeBoxAction("box", Cell(*pick), Cell(*release))


def lift(row, col):
    return RopeBoxAction("rope", Cell(row, col), Cell(row, col))


def test_the_rules_give_100_states_400_moves_all_reachable_and_undone():
    states = TASK.all_states()
    assert len(states) == 100
    pairs = {(s.green, s.orange) for s in states}
    assert len(pairs) == 52  # the paper's ordered box pairs at most 2 steps apart
    moves = [(s, a) for s in states for a in TASK.legal_actions(s)]
    assert len(moves) == 400 and sum(a.kind == "rope" for _, a in moves) == 96
    undo = TASK.spec.undone(np.stack([TASK.action_to_array(a) for _, a in moves]))
    for (s, a), back in zip(moves, undo, strict=True):
        assert TASK.apply(TASK.apply(s, a), TASK.array_to_action(back)) == s
    assert optimal_moves(TASK, states[0], states[-1]) is not None
    seen, todo = {states[0]}, [states[0]]
    while todo:
        for _, nxt in TASK.neighbours(todo.pop()):
            if nxt not in seen:
                seen.add(nxt)
                todo.append(nxt)
    assert len(seen) == 100


def test_codecs_round_trip():
    for s in TASK.all_states():
        assert TASK.parse_state(TASK.state_to_json(s)) == s
        assert TASK.array_to_state(TASK.state_to_array(s)) == s
        for a in TASK.legal_actions(s):
            assert TASK.parse_action(TASK.action_to_json(a)) == a
            assert TASK.array_to_action(TASK.action_to_array(a)) == a
    assert TASK.array_to_action(TASK.action_to_array(None)) is None


def test_a_diagonal_pair_has_the_rope_left_or_right_of_the_pillar_between_them():
    with pytest.raises(InvalidStateError, match="stands between the boxes"):
        state((0, 0), (1, 1))
    left, right = (
        state((0, 0), (1, 1), bent(0, 0, "left")),
        state((0, 0), (1, 1), bent(0, 0, "right")),
    )
    assert TASK.apply(left, lift(0, 0)) == right and TASK.apply(right, lift(0, 0)) == left


def test_lifting_over_a_pillar_beside_a_straight_rope_bends_it_round_and_back():
    straight = state((0, 0), (0, 1))
    # green left of orange, the pillar below their edge: the rope goes under it, turning left
    around = TASK.apply(straight, lift(0, 0))
    assert TASK.state_to_json(around)["rope"] == bent(0, 0, "left")
    assert TASK.apply(around, lift(0, 0)) == straight
    with pytest.raises(IllegalActionError, match="stretched"):
        TASK.apply(straight, lift(0, 1))  # round the far pillar: 2.29 cells of rope
    with pytest.raises(InvalidStateError, match="only bend round pillar"):
        state((0, 0), (0, 1), bent(0, 0, "right"))


def test_pushing_a_box_round_a_pillar_carries_the_rope_with_it():
    # the rope left of pillar (0, 0) between diagonal boxes; orange pushed up beside green:
    # the rope, dragged round the pillar's far side, is bent round it
    s = state((0, 0), (1, 1), bent(0, 0, "right"))
    assert TASK.apply(s, push((1, 1), (0, 1))) == state((0, 0), (0, 1))
    s = state((0, 0), (1, 1), bent(0, 0, "left"))
    assert TASK.apply(s, push((1, 1), (0, 1))) == state((0, 0), (0, 1), bent(0, 0, "left"))


@pytest.mark.parametrize(
    ("boxes", "action", "message"),
    [
        (((0, 0), (0, 1)), push((0, 0), (0, 1)), "other box stands"),
        (((0, 0), (0, 1)), push((0, 0), (1, 1)), "not next to"),
        (((0, 0), (0, 1)), push((1, 0), (2, 0)), "no box in the pick cell"),
        (((0, 0), (0, 2)), push((0, 0), (1, 0)), "3 steps apart"),
        (((0, 0), (0, 2)), lift(1, 1), r"stretched over 3.70 cells \(it is 2.25 long\)"),
    ],
)
def test_illegal_moves_name_the_rule(boxes, action, message):
    with pytest.raises(IllegalActionError, match=message):
        TASK.check_action(state(*boxes), action)


def test_a_rope_action_from_an_array_lifts_at_its_pick_whatever_its_release_says():
    """An APN predicts every field; a rope action's release means nothing (an APN's rope
    action with another release crashed `lsr eval apn` on a 1000-tuple model)."""
    s = state((0, 0), (1, 1), bent(0, 0, "left"))
    lifted = TASK.array_to_action(np.array([KINDS.index("rope"), 0, 0, 2, 1], np.int8))
    assert lifted == lift(0, 0) and TASK.apply(s, lifted) == TASK.apply(s, lift(0, 0))
    with pytest.raises(IllegalActionError, match=r"no pillar at \(2, 2\)"):
        TASK.check_action(s, RopeBoxAction("rope", Cell(2, 2), Cell(2, 2)))
    with pytest.raises(IllegalActionError, match="release is its pillar"):
        TASK.check_action(s, lift(0, 0)._replace(release=Cell(0, 1)))


@pytest.mark.parametrize(
    ("obj", "message"),
    [
        ({"boxes": {"green": {"row": 0, "col": 0}}, "rope": None}, "cells of"),
        (
            {
                "boxes": {"green": {"row": 0, "col": 0}, "orange": {"row": 0, "col": 0}},
                "rope": None,
            },
            "both boxes in one cell",
        ),
        (
            {
                "boxes": {"green": {"row": 0, "col": 0}, "orange": {"row": 2, "col": 2}},
                "rope": None,
            },
            "4 steps apart",
        ),
        (
            {
                "boxes": {"green": {"row": 0, "col": 0}, "orange": {"row": 0, "col": 3}},
                "rope": None,
            },
            "state.boxes.orange.col",
        ),
        (
            {
                "boxes": {"green": {"row": 0, "col": 0}, "orange": {"row": 0, "col": 1}},
                "rope": {"pillar": {"row": 2, "col": 0}, "turn": "left"},
            },
            "state.rope.pillar.row",
        ),
        (
            {
                "boxes": {"green": {"row": 0, "col": 0}, "orange": {"row": 0, "col": 1}},
                "rope": {"pillar": {"row": 0, "col": 0}, "turn": "up"},
            },
            "state.rope.turn",
        ),
        ({"stacks": []}, "'boxes' and 'rope'"),
    ],
)
def test_bad_states_name_what_is_wrong(obj, message):
    with pytest.raises(InvalidStateError, match=message):
        TASK.parse_state(obj)


def test_bad_actions_name_the_field():
    with pytest.raises(InvalidActionError, match=r"action\.kind"):
        TASK.parse_action({"kind": "fold"})
    with pytest.raises(InvalidActionError, match=r"action\.pillar\.col"):
        TASK.parse_action({"kind": "rope", "pillar": {"row": 0, "col": 2}})
    with pytest.raises(InvalidActionError, match="'kind', 'pick' and 'release'"):
        TASK.parse_action({"kind": "box", "pick": {"row": 0, "col": 0}})
    with pytest.raises(InvalidStateError, match="rope = 9"):
        TASK.array_to_state(np.array([0, 0, 0, 1, 9], np.int8))


def test_info_reports_the_counts():
    info = TASK.info()
    assert (info["num_states"], info["num_views"], info["num_transitions"]) == (100, 100, 400)
    assert info["markers"] is not None and len(info["pillars"]) == 4
