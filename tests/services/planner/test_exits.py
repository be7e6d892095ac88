"""Exits: one step of memory for nodes that stand for look-alike states."""

import itertools
from dataclasses import replace

import numpy as np
import pytest

from services.planner.exits import action_exits, forbidden_turns, memory_paths
from services.planner.roadmap import Roadmap, RoadmapError

from .test_roadmap import grid_roadmap, make_roadmap


def equal(x, y):
    return bool(np.array_equal(x, y))


def test_exits_name_each_node_s_actions_by_class():
    # tuples: node 0 -(A)-> 1, 0 -(A')-> 2 with A' the same action as A, 0 -(B)-> 3,
    # a no-action pair, and a tuple whose image fell in no node
    point_node = np.array([0, 1, 0, 2, 0, 3, 1, 1, 0, -1])
    a = np.array([1, 1, 1, 0, 1])
    u = np.array([[1, 0], [1, 1], [5, 5], [-1, -1], [1, 0]])
    same = lambda x, y: x[0] == y[0]  # noqa: E731 - the first field names the action
    assert action_exits(point_node, a, u, same).tolist() == [[0, 1, 0], [0, 2, 0], [0, 3, 1]]
    assert action_exits(point_node, a, u, equal).tolist() == [[0, 1, 0], [0, 2, 1], [0, 3, 2]]


def test_a_turn_is_forbidden_when_the_way_on_is_the_way_back():
    # node 1 looks alike for two states: action 0 leads back to 0 or on to 2; action 1 to 3
    exits = np.array([[1, 0, 0], [1, 2, 0], [1, 3, 1], [0, 1, 2], [2, 1, 2]])
    turns = forbidden_turns(exits, np.arange(4))
    assert turns == {(0, 1): {2}, (2, 1): {0}}  # 3 is reached by another action: allowed
    # an action leading to two nodes of one twin group is one destination
    assert forbidden_turns(exits, np.array([0, 1, 0, 3])) == {}


def test_a_turn_is_forbidden_when_the_way_on_undoes_the_way_in():
    # one state split into nodes 0 and 2 by the encoder: both go into 1 by action 5, which
    # action 6 undoes, but the data saw 1 -(6)-> 0 only; 1 -(7)-> 3 is another move
    exits = np.array([[0, 1, 5], [2, 1, 5], [1, 0, 6], [1, 3, 7], [3, 1, 8]])
    turns = forbidden_turns(exits, np.arange(4))
    assert turns[(2, 1)] == {0}  # back where it came from, not at the other split node
    assert 3 not in turns.get((0, 1), set()) and 3 not in turns.get((2, 1), set())
    assert (3, 1) not in turns  # nothing seen undoes 8


def plain(roadmap, s, t, banned=(), max_paths=100):
    indptr, indices = roadmap._neighbour_arrays()
    return memory_paths(indptr, indices, {}, s, t, banned, max_paths)


def test_without_turns_memory_paths_are_the_roadmap_s_shortest_paths():
    rng = np.random.default_rng(0)
    for _ in range(30):
        k = 9
        edges = {tuple(sorted(e)) for e in rng.integers(k, size=(14, 2)).tolist() if e[0] != e[1]}
        roadmap = make_roadmap(np.zeros((k, 2)), edges)
        for s, t in itertools.permutations(range(k), 2):
            assert plain(roadmap, s, t) == roadmap.shortest_paths(s, t, max_paths=100)
        banned = [(int(x), int(y)) for x, y in roadmap.edges[:2]]
        found = plain(roadmap, 0, k - 1, banned)
        if found:  # (where none is left the roadmap lets banned steps go)
            assert found == roadmap.shortest_paths(0, k - 1, 100, banned)


def test_paths_take_no_forbidden_turn_and_may_start_anywhere():
    grid = grid_roadmap(2, 3)  # 0 1 2 / 3 4 5
    # 1 stands for two look-alike states: the action back to 0 is also the action on to 2
    exits = np.array([[1, 0, 0], [1, 2, 0], [1, 4, 1]])
    roadmap = replace(grid, exits=exits)
    assert roadmap.turns == {(0, 1): {2}, (2, 1): {0}}
    assert roadmap.shortest_paths(0, 2) == [[0, 1, 4, 5, 2], [0, 3, 4, 1, 2], [0, 3, 4, 5, 2]]
    assert roadmap.shortest_paths(0, 5) == [[0, 1, 4, 5], [0, 3, 4, 5]]  # 0 1 2 5 turns
    assert roadmap.shortest_paths(1, 2) == [[1, 2]]  # from 1 itself: some state of it does
    assert roadmap.shortest_paths(4, 2) == grid.shortest_paths(4, 2)
    # avoided steps are let go as before, forbidden turns never
    assert roadmap.shortest_paths(0, 2, avoid=[(0, 3)]) == [[0, 1, 4, 5, 2]]


def test_exits_are_saved_checked_and_kept_apart_from_old_roadmaps(tmp_path):
    grid = grid_roadmap(2, 3)
    roadmap = replace(grid, exits=np.array([[1, 0, 0], [1, 2, 0]]))
    roadmap.save(tmp_path / "r")
    back = Roadmap.load(tmp_path / "r")
    assert back.exits.tolist() == roadmap.exits.tolist() and back.turns == roadmap.turns
    grid.save(tmp_path / "g")  # no exits: none written, none read
    assert Roadmap.load(tmp_path / "g").exits.shape == (0, 3)
    for bad, words in (
        (np.array([[0, 9, 0]]), "exits must hold node ids"),
        (np.array([[0, 1, -1]]), "action classes >= 0"),
        (np.array([[0, 1, 0], [0, 1, 0]]), "exits must be unique"),
        (np.zeros((1, 2), np.int64), "exits must have shape"),
    ):
        with pytest.raises(RoadmapError, match=words):
            replace(grid, exits=bad.astype(np.int64))
