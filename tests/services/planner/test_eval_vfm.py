"""Evaluation on a roadmap whose truth is known, and the whole CLI path on tiny models."""

import json
from dataclasses import replace

import numpy as np
import pytest

from services.cli import main
from services.planner.evaluate import (
    evaluate_plans,
    label_nodes,
    sample_test_pairs,
    shows_everything,
)
from services.planner.exits import action_exits
from services.planner.members import interleave
from services.planner.roadmap import RoadmapConfig, build_roadmap
from services.sim.datagen import GenerateConfig, generate
from shared.tasks import get_task
from shared.tasks.base import optimal_moves

TASK = get_task("box_stacking")


@pytest.fixture(scope="module")
def synthetic():
    """Latents that separate every state perfectly: the roadmap must give only correct plans."""
    rng = np.random.default_rng(0)
    states = TASK.all_states()
    centres = rng.normal(0, 10, (len(states), 16))
    index = {s: i for i, s in enumerate(states)}
    z1, z2, a, s1, s2 = [], [], [], [], []
    for _ in range(3000):
        s = states[int(rng.integers(len(states)))]
        moves = TASK.neighbours(s)
        act = rng.random() < 0.65
        t = moves[int(rng.integers(len(moves)))][1] if act else s
        z1.append(centres[index[s]] + rng.normal(0, 0.05, 16))
        z2.append(centres[index[t]] + rng.normal(0, 0.05, 16))
        a.append(int(act))
        s1.append(TASK.state_to_array(s))
        s2.append(TASK.state_to_array(t))
    z1, z2, a = np.array(z1), np.array(z2), np.array(a)
    roadmap = build_roadmap(z1, z2, a, RoadmapConfig(metric="l1", w_eps=1.0, min_samples=3))
    labels = label_nodes(
        roadmap.point_node, interleave(np.array(s1), np.array(s2)), roadmap.num_nodes
    )
    test_states = np.stack([TASK.state_to_array(s) for s in states])
    z_test = centres + rng.normal(0, 0.05, centres.shape)
    return roadmap, labels, z_test, test_states


def test_perfect_latents_give_perfect_plans(synthetic):
    roadmap, labels, z_test, test_states = synthetic
    assert roadmap.num_nodes == 288 and (labels.purity == 1).all()
    pairs = sample_test_pairs(len(z_test), 200, seed=1)
    result = evaluate_plans("box_stacking", roadmap, labels, z_test, test_states, pairs, 50)
    assert (result["all"], result["any"], result["trans"]) == (100.0, 100.0, 100.0)
    assert result["by_state"] == {"all": 100.0, "any": 100.0, "trans": 100.0}  # nothing hides
    # Detours: the roadmap's plans against the fewest legal moves, pair by pair.
    ratios = []
    for i, j in pairs:
        start, goal = (TASK.array_to_state(test_states[k]) for k in (i, j))
        plan = roadmap.shortest_paths(*(int(roadmap.nearest_node(z_test[k])) for k in (i, j)))
        ratios.append((len(plan[0]) - 1) / optimal_moves(TASK, start, goal))
    assert result["detour_ratio"] == pytest.approx(np.mean(ratios)) and min(ratios) >= 1.0
    reads = labels.states.copy()
    result = evaluate_plans("box_stacking", roadmap, labels, z_test, test_states, pairs, 50, reads)
    assert result["decoded_agreement"] == 100.0


def test_a_wrong_node_label_is_caught(synthetic):
    roadmap, labels, z_test, test_states = synthetic
    swapped = type(labels)(labels.states.copy(), labels.purity, labels.members)
    swapped.states[[0, 1]] = swapped.states[[1, 0]]
    pairs = sample_test_pairs(len(z_test), 300, seed=2)
    result = evaluate_plans("box_stacking", roadmap, swapped, z_test, test_states, pairs, 50)
    assert result["any"] < 100.0 and result["trans"] < 100.0


def test_latents_that_see_only_views_give_right_plans_by_view_not_by_state():
    """The T-shirt as a camera sees it: states that look alike share one latent centre. Judged
    by views every plan is right once the roadmap remembers where its nodes' actions lead
    (exits); without that memory it plans through look-alike states by turns no chain of moves
    takes. The per-state figures (by_state) cannot all be right."""
    shirt = get_task("tshirt_folding")
    rng = np.random.default_rng(0)
    states = shirt.all_states()
    views = sorted({shirt.view(s) for s in states}, key=str)
    centres = {v: rng.normal(0, 10, 16) for v in views}
    z1, z2, a, u, s1, s2 = [], [], [], [], [], []
    for _ in range(3000):
        s = states[int(rng.integers(len(states)))]
        moves = shirt.neighbours(s)
        act = rng.random() < 0.65
        move, t = moves[int(rng.integers(len(moves)))] if act else (None, s)
        z1.append(centres[shirt.view(s)] + rng.normal(0, 0.05, 16))
        z2.append(centres[shirt.view(t)] + rng.normal(0, 0.05, 16))
        a.append(int(act))
        u.append(shirt.action_to_array(move))
        s1.append(shirt.state_to_array(s))
        s2.append(shirt.state_to_array(t))
    a = np.array(a)
    plain = build_roadmap(np.array(z1), np.array(z2), a, RoadmapConfig("l1", 1.0, min_samples=3))
    exits = action_exits(plain.point_node, a, np.array(u), shirt.same_action)
    roadmap = replace(plain, exits=exits)
    point_states = interleave(np.array(s1), np.array(s2))
    labels = label_nodes(roadmap.point_node, point_states, roadmap.num_nodes, shirt)
    assert roadmap.num_nodes == 25 and (labels.purity == 1).all()  # one node a view
    test_states = np.stack([shirt.state_to_array(s) for s in states])
    z_test = np.stack([centres[shirt.view(s)] for s in states]) + rng.normal(0, 0.05, (32, 16))
    pairs = sample_test_pairs(len(states), 300, seed=1)
    result = evaluate_plans("tshirt_folding", roadmap, labels, z_test, test_states, pairs, 50)
    assert (result["all"], result["any"], result["trans"]) == (100.0, 100.0, 100.0)
    assert result["by_state"]["all"] < 100.0 and result["by_state"]["any"] < 100.0
    forgetful = evaluate_plans("tshirt_folding", plain, labels, z_test, test_states, pairs, 50)
    assert forgetful["all"] < 95.0 and forgetful["trans"] == 100.0  # every step alone is legal


def test_pairs_with_a_hidden_end_are_told_apart():
    shirt = get_task("tshirt_folding")
    states = np.stack(
        [shirt.state_to_array(s) for s in [(), ("left_side", "bottom_half"), ("bottom_half",)]]
    )
    pairs = np.array([[0, 2], [0, 1], [1, 2], [2, 0]])
    assert shows_everything(shirt, states)[pairs].all(1).tolist() == [True, False, False, True]


def test_cli_eval_on_tiny_models(tiny_model, tmp_path, capsys):
    model, train = tiny_model
    test = tmp_path / "test"
    generate(GenerateConfig(pairs=10, seed=2, image_size=32, workers=1), test, progress=False)
    reader = tmp_path / "reader"
    assert (
        main(["train", "reader", "--data", str(train), "--out", str(reader), "--epochs", "1"]) == 0
    )
    capsys.readouterr()
    figure = tmp_path / "dist.png"
    assert (
        main(
            [
                "eval",
                "vfm",
                "--model",
                str(model),
                "--test",
                str(test),
                "--pairs",
                "20",
                "--reader",
                str(reader),
                "--train",
                str(train),
                "--json",
                "--figure",
                str(figure),
            ]
        )
        == 0
    )
    row = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in (
        "all",
        "any",
        "trans",
        "nodes",
        "edges",
        "decoded_agreement",
        "interpolation",
        "node_purity_mean",
        "by_state",
        "num_views",
        "mean_min_inter_minus_max_intra",
    ):
        assert key in row
    assert 0 <= row["any"] <= 100 and row["all"] <= row["any"]
    assert "shown_pairs" not in row  # a box-stacking image shows every part of its state
    assert 0 <= row["pairs_known"] <= 100 and 0 <= row["known_images"] <= 100
    if row["pairs_known"] > 0:  # the known pairs' plans, and Table I with refusal on
        assert row["known_pairs"]["pairs"] == round(row["pairs"] * row["pairs_known"] / 100)
        assert row["refusal_on"]["all"] <= row["known_pairs"]["all"]
    assert figure.read_bytes()[:4] == b"\x89PNG"


def test_eval_rejects_a_test_set_of_another_size(tiny_model, tmp_path, capsys):
    model, _ = tiny_model
    test = tmp_path / "test"
    generate(GenerateConfig(pairs=4, seed=2, image_size=16, workers=1), test, progress=False)
    assert main(["eval", "vfm", "--model", str(model), "--test", str(test)]) == 2
    assert "16 px" in capsys.readouterr().err


def test_a_roadmap_without_nodes_scores_zero():
    z = np.zeros((6, 4))
    a = np.array([0, 0, 1, 1, 0, 1])
    roadmap = build_roadmap(z, z, a, RoadmapConfig(min_samples=3))  # one region, no edge
    assert roadmap.num_nodes == 0
    labels = type(label_nodes(roadmap.point_node, np.zeros((12, 3, 3), np.int8), 0))
    empty = labels.from_json(TASK, [])
    assert empty.states.shape == (0, 3, 3)
    result = evaluate_plans(
        "box_stacking", roadmap, empty, z, np.zeros((6, 3, 3), np.int8), np.array([[0, 1]]), 5
    )
    assert (result["all"], result["any"], result["no_path"]) == (0.0, 0.0, 1)


def test_cloth_pipeline_evaluates_and_plans(tiny_cloth_model, tmp_path, capsys):
    """The box-stacking evaluations run unchanged on the cloth task: Table I with a state
    reader, plans with fold arrows, and Table III in the closed loop."""
    from services.planner.action_plans import ActionPlanner
    from services.planner.build import load_labels
    from services.sim.closed_loop import PlanJudge, evaluate_system
    from services.sim.cloth_folding.world import ClothFoldingWorld

    model, train = tiny_cloth_model
    reader = tmp_path / "reader"
    assert (
        main(["train", "reader", "--data", str(train), "--out", str(reader), "--epochs", "1"]) == 0
    )
    capsys.readouterr()
    args = ["eval", "vfm", "--model", str(model), "--test", str(train), "--pairs", "20"]
    assert main([*args, "--reader", str(reader), "--json"]) == 0
    row = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert 0 <= row["all"] <= row["any"] <= 100 and "decoded_agreement" in row

    out = tmp_path / "plans"
    states = ['{"folds": ["top_left"]}', '{"folds": ["bottom_right"]}']
    assert main(["plan", "--model", str(model), "--out", str(out), "--start-state", states[0],
                 "--goal-state", states[1]]) == 0  # fmt: skip
    for plan in json.loads((out / "plans.json").read_text())["plans"]:
        assert all(set(a) == {"pick", "release", "height"} for a in plan["actions"])

    planner = ActionPlanner.from_model_dir(model)
    labels = load_labels(model / "roadmap", "cloth_folding")
    judge = PlanJudge(planner.task, [planner.task.array_to_state(s) for s in labels.states])
    with ClothFoldingWorld(image_size=32, lattice=7) as world:
        result = evaluate_system(planner, world, planner.task, 2, max_steps=3, judge=judge)
    assert sum(result["outcomes"].values()) == 2
    assert set(result["table3"]) == {"system", "transitions", "transitions_as_seen", "vfm", "apn"}
