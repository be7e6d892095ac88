import json
from dataclasses import replace

import numpy as np
import pytest

from services.cli import main
from services.planner.action_plans import ActionPlanner
from services.planner.sheets import plan_sheet
from shared.dataset import load_dataset
from shared.images import encode_png
from shared.plans import VisualActionPlan, most_confident


def test_plans_have_one_action_per_step(tiny_model):
    model_dir, data_dir = tiny_model
    planner = ActionPlanner.from_model_dir(model_dir)
    data = load_dataset(data_dir)
    plans = planner.plan(data.image1[0], data.image2[5], max_plans=3)
    assert 1 <= len(plans) <= 3 or plans == []
    for plan in plans:
        assert len(plan.images) == len(plan.nodes) == len(plan.actions) + 1
        assert len(plan.confidences) == len(plan.actions)
        assert all(image.shape == (32, 32, 3) for image in plan.images)
        json.dumps(plan.to_json(planner.task))
    assert [p.nodes for p in plans] == [
        p.nodes for p in planner.plan(data.image1[0], data.image2[5], 3)
    ]


def test_most_confident_prefers_the_surest_first_action():
    plans = [
        VisualActionPlan([0, 1], [], ["a"], [0.6], [1]),
        VisualActionPlan([0, 2], [], ["b"], [0.9], [1]),
        VisualActionPlan([0, 3], [], ["c"], [0.9], [1]),
    ]
    assert most_confident(plans).nodes == [0, 2]


def test_a_plans_confidence_is_the_product_of_its_actions():
    from shared.tasks.box_stacking import BoxStacking, Cell, Move

    move = Move(Cell(0, 0), Cell(0, 1))
    plan = VisualActionPlan([0, 1, 2], [], [move, move], [0.9, 0.5], [1, 1])
    assert plan.confidence == pytest.approx(0.45)
    assert plan.to_json(BoxStacking())["confidence"] == pytest.approx(0.45)
    assert VisualActionPlan([3], [], [], [], []).confidence == 1.0  # already at the goal


def test_a_plans_support_falls_with_length_and_rises_with_evidence():
    from shared.tasks.box_stacking import BoxStacking, Cell, Move

    move = Move(Cell(0, 0), Cell(0, 1))
    seen_once = VisualActionPlan([0, 1], [], [move], [1.0], [1])
    assert seen_once.support == pytest.approx(2 / 3)
    two_steps = VisualActionPlan([0, 1, 2], [], [move, move], [1.0, 1.0], [1, 1])
    assert two_steps.support == pytest.approx(4 / 9)
    assert VisualActionPlan([0, 1], [], [move], [1.0], [98]).support == pytest.approx(0.99)
    document = two_steps.to_json(BoxStacking())
    assert document["supports"] == [1, 1] and document["support"] == pytest.approx(4 / 9, abs=1e-6)
    assert VisualActionPlan([3], [], [], [], []).support == 1.0


def test_sheet_marks_pick_and_release():
    from shared.tasks.box_stacking import Cell, Move

    images = [np.full((32, 32, 3), 200, np.uint8)] * 2
    plan = VisualActionPlan([4, 7], images, [Move(Cell(0, 0), Cell(1, 2))], [0.99], [1])

    def cells(move):
        return [(8.0 + 8 * c.col, 24.0 - 8 * c.row) for c in move]

    sheet = plan_sheet(plan, cells, scale=3)
    assert sheet.shape == (96 + 30, 2 * (96 + 4), 3)
    blue = (sheet[:, :, 2] > 200) & (sheet[:, :, 0] < 100)
    green = (sheet[:, :, 1] > 150) & (sheet[:, :, 0] < 100) & (sheet[:, :, 2] < 100)
    assert blue.any() and green.any()


def test_sheet_draws_a_fold_as_an_arrow_from_pick_to_release():
    from shared.tasks.cloth_folding import ClothAction, Pixel

    images = [np.full((32, 32, 3), 200, np.uint8)] * 2
    fold = ClothAction(Pixel(4, 4), Pixel(28, 28), 0)
    plan = VisualActionPlan([0, 1], images, [fold], [0.9], [1])
    sheet = plan_sheet(plan, lambda a: ((4.5, 4.5), (28.5, 28.5)), arrows=True, scale=3)
    green = (sheet[:, :, 1] > 150) & (sheet[:, :, 0] < 100) & (sheet[:, :, 2] < 100)
    on_diagonal = [green[k, k] for k in range(30, 80)]  # the shaft runs along the diagonal
    assert all(on_diagonal) and not green[80:96, :20].any()


def test_cli_plan_from_states_and_images(tiny_model, tmp_path):
    model_dir, data_dir = tiny_model
    out = tmp_path / "plans"
    rc = main(
        [
            "plan",
            "--model",
            str(model_dir),
            "--out",
            str(out),
            "--start-state",
            '{"stacks": [["red", "green"], ["blue"], ["yellow"]]}',
            "--goal-state",
            '{"stacks": [["red"], ["green", "blue"], ["yellow"]]}',
        ]
    )
    assert rc == 0
    summary = json.loads((out / "plans.json").read_text())
    assert len(list(out.glob("plan_*.png"))) == len(summary["plans"])
    image = tmp_path / "start.png"
    image.write_bytes(encode_png(load_dataset(data_dir).image1[0]))
    assert (
        main(
            [
                "plan",
                "--model",
                str(model_dir),
                "--out",
                str(tmp_path / "p2"),
                "--start-image",
                str(image),
                "--goal-image",
                str(image),
            ]
        )
        == 0
    )


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (
            [
                "--start-state",
                '{"stacks": [["red"], ["red"], []]}',
                "--goal-state",
                '{"stacks": [["red", "green", "blue", "yellow"], [], []]}',
            ],
            "appears twice",
        ),
        (
            [
                "--start-image",
                "SMALL",
                "--goal-state",
                '{"stacks": [["red"], ["green", "blue"], ["yellow"]]}',
            ],
            "--start-image is not known: the table markers were not found: 0 of 4",
        ),
        (
            ["--goal-state", '{"stacks": [["red"], ["green", "blue"], ["yellow"]]}'],
            "exactly one of --start-image and --start-state",
        ),
    ],
)
def test_cli_plan_bad_input(tiny_model, tmp_path, capsys, args, message):
    model_dir, _ = tiny_model
    small = tmp_path / "small.png"
    small.write_bytes(encode_png(np.zeros((16, 16, 3), np.uint8)))
    args = [str(small) if a == "SMALL" else a for a in args]
    assert main(["plan", "--model", str(model_dir), "--out", str(tmp_path / "o"), *args]) == 2
    assert message in capsys.readouterr().err


def test_edge_actions_apply_the_apn_to_every_edge_both_ways(monkeypatch):
    import services.planner.action_plans as action_plans
    from services.planner.roadmap import Roadmap, RoadmapConfig
    from shared.tasks import get_task

    task = get_task("box_stacking")
    s0 = task.sample_state(np.random.default_rng(0))
    s1 = task.neighbours(s0)[0][1]
    s2 = next(t for _, t in task.neighbours(s1) if t != s0)
    states = [s0, s1, s2]
    moves = {
        (a, b): next(m for m, t in task.neighbours(states[a]) if t == states[b])
        for a, b in [(0, 1), (1, 0), (1, 2), (2, 1)]
    }
    moves[(2, 1)] = moves[(1, 2)]  # the APN gets one direction wrong
    roadmap = Roadmap(
        config=RoadmapConfig(metric="l1"),
        epsilon=1.0,
        mu0=0.5,
        sigma0=0.1,
        nodes=np.array([[0.0], [1.0], [2.0]], np.float32),
        node_sizes=np.ones(3, np.int64),
        edges=np.array([[0, 1], [1, 2]], np.int64),
        edge_weights=np.ones(2, np.int64),
        point_node=np.array([0, 1, 1, 2], np.int64),
    )

    def propose(apn, z1, z2):  # a fake APN that knows the move of each edge
        keys = zip(z1[:, 0].astype(int), z2[:, 0].astype(int), strict=True)
        arrays = np.stack([task.action_to_array(moves[k]) for k in keys])
        return arrays, np.ones(len(arrays))

    monkeypatch.setattr(action_plans, "propose", propose)
    result = action_plans.edge_actions(task, roadmap, None, states)
    assert (result["edges"], result["right"]) == (4, 3)
    # node 3 is node 1's twin (one state): plans step 1 -> 2 over the edge 3 - 2, so that is judged
    twinned = replace(
        roadmap,
        nodes=np.array([[0.0], [1.0], [2.0], [3.0]], np.float32),
        node_sizes=np.ones(4, np.int64),
        edges=np.array([[0, 1], [2, 3]], np.int64),
        point_node=np.array([0, 1, 3, 2], np.int64),
        twins=np.array([[1, 3]], np.int64),
    )
    assert action_plans.edge_actions(task, twinned, None, [*states, s1]) == result
    assert result["wrong"] == [
        {
            "from": task.state_to_json(s2),
            "to": task.state_to_json(s1),
            "action": task.action_to_json(moves[(1, 2)]),
        }
    ]
