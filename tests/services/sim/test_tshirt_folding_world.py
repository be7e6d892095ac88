"""The T-shirt world at full size: resets come from the shipped settled-state library
(models/tshirt_folding/settled), so only the moves a test makes cost physics (about a second
each)."""

import numpy as np
import pytest

from services.sim.tshirt_folding.world import TshirtFoldingWorld
from shared.tasks.base import IllegalActionError, InvalidActionError, WorldError
from shared.tasks.folding import ClothAction, Pixel


@pytest.fixture(scope="module")
def shirt():
    w = TshirtFoldingWorld(image_size=32)
    yield w
    w.close()


def test_the_shipped_library_holds_every_fold_order(shirt):
    assert shirt.library.source is not None, "run: lsr settle --task tshirt_folding"
    assert shirt.library.complete(shirt)


def test_every_state_resets_and_reads_back_part_by_part(shirt):
    rng = np.random.default_rng(0)
    images = {}
    for state in shirt.task.all_states():
        assert shirt.reset(state, rng) == state
        shares = sorted(shirt.far_shares().values())
        # its own reference in every part, then the nearest other state by a wide margin
        assert shares[0] < 0.2 and shares[1] > 0.45  # measured: at most 13%, at least 50%
        images[state] = shirt.render()
    flat = images[()].astype(int)
    assert all(np.abs(flat - img).sum() > 500 for s, img in images.items() if s)


def test_a_sleeve_hidden_in_its_side_flap_is_told_from_one_on_top(shirt):
    rng = np.random.default_rng(1)
    hidden = ("left_sleeve", "left_side")
    assert shirt.reset(hidden, rng) == hidden
    assert shirt.far_shares()[("left_side",)] > 0.5  # the sleeve part is all wrong


def test_fold_a_sleeve_into_its_side_then_unfold_both_with_noisy_clicks(shirt):
    rng = np.random.default_rng(2)
    task = shirt.task
    state = shirt.reset(("left_sleeve",), rng)
    for kind, fold in (("fold", "left_side"), ("unfold", "left_side"), ("unfold", "left_sleeve")):
        action = shirt.demonstrated(task.moves[kind, fold].action, rng)
        expected = task.apply(state, action)
        state = shirt.execute(action, rng)
        assert state == expected
    assert state == ()


def test_the_bottom_half_folds_over_both_sides(shirt):
    rng = np.random.default_rng(3)
    start = ("right_sleeve", "left_side", "right_side")
    shirt.reset(start, rng)
    fold = shirt.demonstrated(shirt.task.moves["fold", "bottom_half"].action, rng)
    assert shirt.execute(fold, rng) == (*start, "bottom_half")


def _off_reference_cm(shirt, state) -> float:
    """95th percentile of the vertices' distance from the state's ideal shape, posed."""
    points = shirt.vertices()
    rotation, centroid, target = shirt.pose(points, state)
    posed = (points[:, :2] - centroid) @ rotation + target
    return 100 * float(np.percentile(np.linalg.norm(posed - shirt._references[state], axis=1), 95))


def test_a_move_ends_smoothed_so_a_state_looks_the_same_however_reached(shirt):
    rng = np.random.default_rng(5)
    folded, unfolded = ("left_side", "right_side", "bottom_half"), ("left_side", "right_side")
    unfold = shirt.task.moves["unfold", "bottom_half"].action
    try:
        shirt.smooth_after_moves = False
        shirt.reset(folded, rng)
        assert shirt.execute(shirt.demonstrated(unfold, rng), rng) == unfolded
        assert _off_reference_cm(shirt, unfolded) > 1.0  # measured 2.9: the strips dragged
    finally:
        del shirt.smooth_after_moves  # the class's: on
    shirt.reset(folded, rng)
    assert shirt.execute(shirt.demonstrated(unfold, rng), rng) == unfolded
    after_move = _off_reference_cm(shirt, unfolded)
    shirt.reset(unfolded, rng)
    assert after_move < 0.5 and after_move < 3 * _off_reference_cm(shirt, unfolded) + 0.1


def test_an_illegal_action_leaves_the_shirt_as_it_was(shirt):
    rng = np.random.default_rng(4)
    shirt.reset(("left_side",), rng)
    before = shirt.vertices()
    with pytest.raises(IllegalActionError, match="'left_sleeve' cannot fold while 'left_side'"):
        shirt.execute(shirt.task.moves["fold", "left_sleeve"].action, rng)
    with pytest.raises(IllegalActionError, match="no fold or unfold matches"):
        shirt.execute(ClothAction(Pixel(128, 20), Pixel(128, 128), 0), rng)
    assert np.array_equal(shirt.vertices(), before)


def test_a_pick_with_no_top_layer_is_refused_by_name(shirt):
    shirt.reset((), np.random.default_rng(5))
    unfold = shirt.task.moves["unfold", "left_side"].action  # a legal-looking click, flat cloth
    with pytest.raises(InvalidActionError, match="hits no cloth of the folded left_side"):
        shirt.grasp(unfold)


@pytest.mark.parametrize(
    ("state", "kind", "fold", "offset"),
    [
        ((), "fold", "right_side", (0, 7)),  # both clicks 7 px right: a line 1.6 cm off
        (("right_sleeve", "right_side"), "fold", "left_sleeve", (7, -7)),  # the pick off cloth
        (("left_sleeve",), "unfold", "left_sleeve", (0, 9)),  # the pick towards the crease
        (("right_side", "bottom_half"), "unfold", "bottom_half", (-6, 6)),  # off the flap
    ],
)
def test_clicks_anywhere_within_the_tolerance_make_the_move(shirt, state, kind, fold, offset):
    """The click names the move; the hand folds on the garment's own line and takes the
    nearest cloth of the flap (bench_landing.py measures this over every move)."""
    rng = np.random.default_rng(8)
    task = shirt.task
    canonical = task.moves[kind, fold].action
    row, col = offset
    clicked = ClothAction(
        Pixel(canonical.pick.row + row, canonical.pick.col + col),
        Pixel(canonical.release.row + row, canonical.release.col + col),
        canonical.height,
    )
    assert task.match(clicked) is task.moves[kind, fold]
    shirt.reset(state, rng)
    assert shirt.execute(clicked, rng) == task.apply(state, clicked)


def test_a_shirt_that_matches_no_state_names_the_nearest(shirt):
    shirt.reset((), np.random.default_rng(6))
    points = shirt.vertices()
    points[:, :2] *= 0.7
    shirt._set_vertices(points)
    with pytest.raises(WorldError, match="matches no state: nearest is"):
        shirt.read_state()


def test_no_action_perturbation_keeps_the_state(shirt):
    rng = np.random.default_rng(7)
    state = shirt.reset(("right_sleeve", "bottom_half"), rng)
    before = shirt.render()
    assert shirt.perturb(rng) == state
    assert np.abs(shirt.render().astype(int) - before).sum() > 0
