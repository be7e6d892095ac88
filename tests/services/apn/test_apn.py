import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from services.apn.model import APN, APNConfig
from services.apn.train import (
    DEFAULT_STEPS,
    APNTrainConfig,
    evaluate_apn,
    load_apn,
    propose,
    roadmap_node_pairs,
    train_apn,
)
from services.cli import main
from services.planner.roadmap import Roadmap
from shared.checkpoint import verify


@pytest.mark.parametrize("head", ["classify", "regress"])
def test_forward_predict_and_loss(head):
    model = APN(APNConfig(latent_dim=8, head=head))
    z1, z2 = torch.randn(5, 8), torch.randn(5, 8)
    output = model(z1, z2)
    assert output.shape == (5, 12 if head == "classify" else 4)
    action, confidence = model.predict(output)
    assert action.shape == (5, 4) and action.min() >= 0 and action.max() <= 2
    assert ((confidence >= 0) & (confidence <= 1)).all()
    target = torch.randint(0, 3, (5, 4))
    model.loss(output, target).backward()


def test_regression_rounds_to_cells():
    model = APN(APNConfig(latent_dim=2, head="regress"))
    # sigmoid(0) = 0.5 -> 1.0 of 0..2: exactly cell 1, full confidence
    action, confidence = model.predict(torch.zeros(1, 4))
    assert action.tolist() == [[1, 1, 1, 1]] and confidence.item() == pytest.approx(1.0)


def test_bad_configs():
    with pytest.raises(ValueError, match="head"):
        APNConfig(head="guess")
    with pytest.raises(ValueError, match="val_fraction"):
        APNTrainConfig(val_fraction=0)
    with pytest.raises(ValueError, match="fractions"):
        APNTrainConfig(lr_drops=(50, 150))  # epochs, as the config had them before issue 14


def test_runs_are_counted_in_steps_whatever_the_data_size():
    cfg = APNTrainConfig()
    assert cfg.total_steps(100) == cfg.total_steps(10_000) == DEFAULT_STEPS
    assert APNTrainConfig(epochs=2).total_steps(130) == 2 * 3  # passes of batches of 64


def test_training_in_steps_validates_every_pass_and_drops_lr(tiny_model, tmp_path):
    model_dir, data = tiny_model

    def run(name: str, cfg: APNTrainConfig) -> tuple[dict, list[dict]]:
        meta = train_apn(model_dir / "vae", data, tmp_path / name, cfg, progress=False)
        lines = (tmp_path / name / "log.jsonl").read_text().splitlines()
        return meta, [json.loads(x) for x in lines]

    # one batch a pass: validated after every step, so the log shows the lr of every step
    meta, log = run("whole", APNTrainConfig(steps=6, batch_size=1024, lr_drops=(0.5,)))
    assert [r["lr"] for r in log] == pytest.approx([1e-2] * 3 + [1e-3] * 3)
    assert meta["best"] in log and meta["train"]["total_steps"] == 6
    # batches of 16: validated after every pass and after the last step
    meta, log = run("batches", APNTrainConfig(steps=7, batch_size=16))
    per_pass = -(-meta["pairs"]["train_samples"] // 16)
    assert [r["step"] for r in log] == sorted({*range(per_pass, 7, per_pass), 7})
    assert load_apn(tmp_path / "batches")[1]["train"]["steps"] == 7


def test_restarts_share_one_split_and_keep_the_lowest_validation_loss(tiny_model, tmp_path):
    model_dir, data = tiny_model
    cfg = APNTrainConfig(steps=4, batch_size=1024, seed=3)
    one = [train_apn(model_dir / "vae", data, tmp_path / f"s{s}", replace(cfg, seed=s),
                     progress=False) for s in (3, 4)]  # fmt: skip
    meta = train_apn(model_dir / "vae", data, tmp_path / "r", replace(cfg, restarts=2), False)
    assert meta["pairs"] == one[0]["pairs"]
    losses = meta["restarts"]["val_loss"]
    assert losses[0] == pytest.approx(one[0]["best"]["val_loss"])  # seed 3 run alone
    assert meta["best"]["val_loss"] == min(losses)
    assert meta["restarts"]["kept_seed"] == 3 + losses.index(min(losses))
    with pytest.raises(ValueError, match="restarts"):
        APNTrainConfig(restarts=0)


def test_train_load_evaluate(tiny_model):
    model_dir, data = tiny_model
    apn, meta = load_apn(model_dir / "apn")
    assert meta["format"] == "lsr-apn" and meta["pairs"]["val"] >= 1
    assert verify(model_dir / "apn")  # written atomically and sealed
    # means + S = 1 draw, of every pair and its reverse (box stacking declares its undo)
    assert meta["train"]["undo"] and meta["pairs"]["train_samples"] == 4 * meta["pairs"]["train"]
    lines = (model_dir / "apn" / "log.jsonl").read_text().splitlines()
    assert [json.loads(x)["epoch"] for x in lines] == [1, 2, 3]
    actions, confidences = propose(apn, np.zeros((2, 64), np.float32), np.ones((2, 64), np.float32))
    assert actions.shape == (2, 4) and confidences.shape == (2,)
    result = evaluate_apn(model_dir / "apn", model_dir / "vae", data)
    assert 0 <= result["both"] <= min(result["pick"], result["release"]) <= 100
    # an action that is exactly right leads to the pair's view (and a few right ones may be
    # right by another cell of the same stack)
    assert result["both"] <= result["leads_to_view"] <= 100


def test_undo_teaches_the_reverse_of_every_pair(tiny_model, tmp_path):
    model_dir, data = tiny_model
    cfg = APNTrainConfig(steps=2, batch_size=1024, samples=0)
    with_undo = train_apn(model_dir / "vae", data, tmp_path / "undo", cfg, progress=False)
    without = train_apn(model_dir / "vae", data, tmp_path / "one", replace(cfg, undo=False), False)
    assert with_undo["pairs"]["train_samples"] == 2 * with_undo["pairs"]["train"]
    assert without["pairs"]["train_samples"] == without["pairs"]["train"]
    assert not without["train"]["undo"]


def test_the_roadmaps_edges_join_the_training_split_only(tiny_model, tmp_path):
    model_dir, data = tiny_model
    cfg = APNTrainConfig(steps=2, batch_size=1024, samples=0)
    n1, n2, u = roadmap_node_pairs(model_dir / "roadmap")
    roadmap = Roadmap.load(model_dir / "roadmap")
    assert len(u) > 0 and u.shape[1] == 4 and (u >= 0).all()  # action pairs only
    nodes = {tuple(z) for z in roadmap.nodes.astype(np.float32)}
    assert all(tuple(z) in nodes for z in np.concatenate([n1, n2]))  # the latents plans ask about
    plain = train_apn(model_dir / "vae", data, tmp_path / "plain", cfg, progress=False)
    meta = train_apn(model_dir / "vae", data, tmp_path / "rm", cfg, False, model_dir / "roadmap")
    assert meta["node_pairs"] == len(u) and plain["node_pairs"] == 0
    # each edge both ways (box stacking declares its undo); validation as before
    assert meta["pairs"]["train_samples"] == plain["pairs"]["train_samples"] + 2 * len(u)
    assert meta["best"]["val_loss"] != plain["best"]["val_loss"]  # it trained on them
    assert main(["train", "apn", "--vae", str(model_dir / "vae"), "--data", str(data),
                 "--roadmap", str(model_dir / "roadmap"), "--steps", "1",
                 "--out", str(tmp_path / "cli")]) == 0  # fmt: skip
    assert load_apn(tmp_path / "cli")[1]["node_pairs"] == len(u)


def test_load_error(tmp_path):
    with pytest.raises(ValueError, match="not an APN folder"):
        load_apn(tmp_path)


def test_hybrid_head_regresses_pixels_and_classifies_the_height():
    sizes = (256, 256, 256, 256, 2)
    model = APN(APNConfig(latent_dim=8, action_sizes=sizes, head="hybrid"))
    assert model.config.regressed == (True, True, True, True, False)
    output = model(torch.randn(6, 8), torch.randn(6, 8))
    assert output.shape == (6, 4 + 2)
    action, confidence = model.predict(output)
    assert action.shape == (6, 5) and action[:, :4].max() <= 255 and action[:, 4].max() <= 1
    assert ((confidence > 0) & (confidence <= 1)).all()  # the height's probability
    model.loss(output, torch.tensor([[40, 200, 128, 128, 1]] * 6)).backward()
    # sigmoid(0) = 0.5 of 0..255 rounds to 128 (127.5 -> 128)
    action, _ = model.predict(torch.zeros(1, 6))
    assert action[0, :4].tolist() == [128] * 4


def test_cloth_apn_reports_table_two(tiny_cloth_model):
    model_dir, data = tiny_cloth_model
    _, meta = load_apn(model_dir / "apn")
    assert meta["model"]["head"] == "hybrid"  # chosen from the dataset's spec: pixels
    assert len(meta["action_scaled"]["std"]) == 5
    result = evaluate_apn(model_dir / "apn", model_dir / "vae", data)
    mse = result["mse"]
    assert mse["total"] >= mse["pick"] + mse["release"] - 1e-9 and mse["pick"] >= 0
    assert result["pick_pixels"]["mean"] >= 0 and 0 <= result["same_move"] <= 100
    noise = result["mse_click_noise"]  # every demonstrated click matches a move
    assert 0 < noise["pick"] <= noise["total"]


def test_cli_steps_or_epochs(tiny_model, tmp_path):
    model_dir, data = tiny_model
    base = ["train", "apn", "--vae", str(model_dir / "vae"), "--data", str(data)]
    assert main([*base, "--steps", "2", "--out", str(tmp_path / "a")]) == 0
    train = load_apn(tmp_path / "a")[1]["train"]
    assert (train["steps"], train["epochs"], train["total_steps"]) == (2, None, 2)
    with pytest.raises(SystemExit):  # one length, not two
        main([*base, "--steps", "2", "--epochs", "1", "--out", str(tmp_path / "b")])


def test_cli_eval_apn_checks_the_roadmap_edges(tiny_model, capsys):
    from services.planner.roadmap import Roadmap

    model_dir, data = tiny_model
    assert main(["eval", "apn", "--model", str(model_dir), "--test", str(data), "--json"]) == 0
    edges = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["roadmap_edges"]
    assert edges["edges"] == 2 * len(Roadmap.load(model_dir / "roadmap").edges)
    assert len(edges["wrong"]) == min(5, edges["edges"] - edges["right"])
