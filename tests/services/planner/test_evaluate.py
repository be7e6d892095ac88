import numpy as np
import pytest

from services.planner.evaluate import (
    TransitionChecker,
    class_distances,
    demonstrated_reach,
    evaluate_interpolation,
    label_nodes,
    path_verdict,
    sample_test_pairs,
)
from shared.tasks import get_task
from shared.tasks.base import optimal_moves

TASK = get_task("box_stacking")
S0 = TASK.parse_state({"stacks": [["red", "green"], [], ["blue", "yellow"]]})
S1 = TASK.parse_state({"stacks": [["red"], ["green"], ["blue", "yellow"]]})
S2 = TASK.parse_state({"stacks": [["red"], ["green", "yellow"], ["blue"]]})


def test_label_nodes_majority_and_purity():
    a, b = TASK.state_to_array(S0), TASK.state_to_array(S1)
    point_states = np.stack([a, a, b, b, b, a])
    labels = label_nodes(np.array([0, 0, 0, 1, 1, -1]), point_states, 2)
    assert np.array_equal(labels.states[0], a) and np.array_equal(labels.states[1], b)
    assert labels.purity.tolist() == [2 / 3, 1.0] and labels.members.tolist() == [3, 2]
    back = type(labels).from_json(TASK, labels.to_json(TASK))
    assert np.array_equal(back.states, labels.states)


def test_path_verdicts():
    checker = TransitionChecker(TASK)
    assert path_verdict(checker, [S0, S1, S2], S0, S2) == (True, 2, 2)
    assert path_verdict(checker, [S0, S2], S0, S2) == (False, 0, 1)  # two moves in one step
    assert path_verdict(checker, [S0, S1], S0, S2) == (False, 1, 1)  # wrong goal
    assert path_verdict(checker, [S0, S0], S0, S0) == (False, 0, 1)  # standing still


SHIRT = get_task("tshirt_folding")


def shirt(*folds):
    return SHIRT.parse_state({"folds": list(folds)})


# With the bottom half folded, the left side hides its sleeve: these two look alike.
SIDE_HALF, HIDDEN_SLEEVE = (
    shirt("left_side", "bottom_half"),
    shirt("left_sleeve", "left_side", "bottom_half"),
)
UNFOLD_HALF = SHIRT.moves["unfold", "bottom_half"].action


def test_paths_and_actions_are_judged_by_views_and_by_state_apart():
    """interface.md, "Views": right when some state showing each view chains the moves."""
    view, state = TransitionChecker(SHIRT), TransitionChecker(SHIRT, by_state=True)
    # the node stands for the view; from the hidden-sleeve state unfolding the half shows it
    path = [SIDE_HALF, shirt("left_sleeve", "left_side")]
    assert path_verdict(view, path, HIDDEN_SLEEVE, path[-1]) == (True, 1, 1)
    assert path_verdict(state, path, HIDDEN_SLEEVE, path[-1]) == (False, 0, 1)
    assert view.actions_lead(path, [UNFOLD_HALF])
    assert not state.actions_lead(path, [UNFOLD_HALF])
    # no state of that view unfolds into a folded right sleeve
    wrong = [SIDE_HALF, shirt("right_sleeve", "left_side")]
    assert path_verdict(view, wrong, SIDE_HALF, wrong[-1]) == (False, 0, 1)
    assert not view.actions_lead(wrong, [UNFOLD_HALF])
    # each step may be legal alone and still no one chain of states run through them all
    a, b = shirt("left_sleeve", "left_side"), shirt("left_side")
    assert view.legal(a, HIDDEN_SLEEVE) and view.legal(HIDDEN_SLEEVE, b)
    assert not view.chain([a, HIDDEN_SLEEVE, b])
    assert view.same(SIDE_HALF, HIDDEN_SLEEVE) and not state.same(SIDE_HALF, HIDDEN_SLEEVE)
    # a plan's actions: from some state showing the start, legal, ending showing the goal
    fold_half = SHIRT.moves["fold", "bottom_half"].action
    assert view.reaches(shirt("left_sleeve", "left_side"), [fold_half], SIDE_HALF)
    assert not state.reaches(shirt("left_sleeve", "left_side"), [fold_half], SIDE_HALF)
    assert view.reaches(SIDE_HALF, [UNFOLD_HALF], shirt("left_sleeve", "left_side"))
    assert not view.reaches(SIDE_HALF, [UNFOLD_HALF, UNFOLD_HALF], shirt("left_side"))
    assert set(view.showing(SIDE_HALF)) == {SIDE_HALF, HIDDEN_SLEEVE}


def test_fewest_moves_to_a_view():
    flat = shirt()
    assert optimal_moves(SHIRT, flat, HIDDEN_SLEEVE) == 2  # the left side, then the half
    assert optimal_moves(SHIRT, flat, HIDDEN_SLEEVE, by_state=True) == 3


def test_a_node_stands_for_the_view_most_of_its_members_show():
    arrays = [SHIRT.state_to_array(s) for s in (SIDE_HALF, HIDDEN_SLEEVE, shirt("right_side"))]
    point_states = np.stack([arrays[0]] * 3 + [arrays[1]] * 2 + [arrays[2]] * 4)
    nodes = np.zeros(len(point_states), np.int64)
    by_view = label_nodes(nodes, point_states, 1, SHIRT)
    assert np.array_equal(by_view.states[0], arrays[0]) and by_view.purity[0] == 5 / 9
    by_state = label_nodes(nodes, point_states, 1)  # no task: the states themselves
    assert np.array_equal(by_state.states[0], arrays[2]) and by_state.purity[0] == 4 / 9


def test_interpolation_counts_unreadable_states_as_wrong():
    states = np.stack([TASK.state_to_array(s) for s in (S0, S2)])
    bad = np.full((3, 3), 7, np.int8)
    good = np.stack([TASK.state_to_array(s) for s in (S0, S1, S2)])
    result = evaluate_interpolation(
        "box_stacking", [good, np.stack([good[0], bad, good[2]])], states, np.array([[0, 1]] * 2)
    )
    assert result["all"] == 50.0 and result["trans"] == 50.0


def test_test_pairs_are_distinct_and_seeded():
    pairs = sample_test_pairs(10, 500, seed=3)
    assert (pairs[:, 0] != pairs[:, 1]).all() and pairs.max() < 10
    assert np.array_equal(pairs, sample_test_pairs(10, 500, seed=3))


def test_class_distances_separated_and_not():
    rng = np.random.default_rng(0)
    centres = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    classes = np.repeat(np.arange(3), 20)
    z = centres[classes] + rng.normal(0, 0.1, (60, 2))
    apart = class_distances(z, classes, "l1")
    assert apart["classes_separated"] == 3 and apart["mean_min_inter_minus_max_intra"] > 9
    mixed = class_distances(rng.normal(0, 1, (60, 2)), classes, "l2")
    assert mixed["classes_separated"] < 3 and mixed["mean_min_inter_minus_max_intra"] < 0


def test_demonstrated_reach_is_the_share_of_pairs_the_training_transitions_chain():
    # states 0-1-2 chained by actions, 3-4 by one action, 5 seen only in a no-action pair
    s1 = np.array([[0], [1], [3], [5]], np.int8)
    s2 = np.array([[1], [2], [4], [5]], np.int8)
    a = np.array([1, 1, 1, 0])
    test = np.array([[0], [2], [3], [4], [5], [6]], np.int64)  # 6: never demonstrated
    pairs = np.array([[0, 1], [2, 3], [0, 2], [4, 4], [5, 0], [3, 2]])
    # 0-2 joined, 3-4 joined, 0-3 not, 5-5 seen (one state), 6 never seen, 4-3 joined
    assert demonstrated_reach(s1, s2, a, test, pairs) == pytest.approx(100.0 * 4 / 6)
    assert demonstrated_reach(s1, s2, np.zeros(4, int), test, pairs[[3]]) == 100.0
