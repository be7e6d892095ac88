"""lsr train model: one dataset to a served model, settings from the dataset, nothing written
for a dataset it cannot train from."""

import json

import numpy as np
import pytest

from services.cli import main
from services.recipe import Recipe, choose, vae_steps
from services.runtime import ModelInfo
from shared.dataset import FORMAT, VERSION, load_dataset, write_manifest, write_shard
from shared.images import encode_png
from shared.tasks import get_task

# Tiny runs: the command's whole path in seconds, not a model that plans well.
TINY = ["--vae-steps", "3", "--apn-steps", "20", "--apn-restarts", "2", "--min-samples", "1"]


def record(task_name, out, pairs=40, size=32, seed=0, settings=None):
    """A recording of a task's own states and moves, each state drawn as a fixed pattern plus
    sensor noise: what the command reads from any recorder, without rendering it."""
    task = get_task(task_name)
    states = list(task.all_states())
    rng = np.random.default_rng(seed)
    patterns = rng.integers(0, 256, (len(states), 4, 4, 3))

    def image(state) -> np.ndarray:
        big = np.kron(patterns[task.state_index(state)], np.ones((size // 4, size // 4, 1)))
        return np.clip(big + rng.normal(0, 4, big.shape), 0, 255).astype(np.uint8)

    rows = {f: [] for f in ("image1", "image2", "a", "u", "state1", "state2")}
    for k in range(pairs):
        first = states[rng.integers(len(states))]
        moves = task.neighbours(first)
        action, second = moves[rng.integers(len(moves))] if k % 3 else (None, first)
        for name, value in (
            ("image1", image(first)),
            ("image2", image(second)),
            ("a", int(action is not None)),
            ("u", task.action_to_array(action)),
            ("state1", task.state_to_array(first)),
            ("state2", task.state_to_array(second)),
        ):
            rows[name].append(value)
    arrays = {f: np.stack(v) if f != "a" else np.array(v, np.uint8) for f, v in rows.items()}
    out.mkdir(parents=True)
    sha = write_shard(out / "shard-00000.npz", arrays, task.spec)
    moved = int(arrays["a"].sum())
    manifest = {
        "format": FORMAT,
        "version": VERSION,
        "task": task_name,
        "spec": task.spec.to_json(),
        "image_size": size,
        "seed": seed,
        "counts": {"tuples": pairs, "action_pairs": moved, "no_action_pairs": pairs - moved},
        "shards": [{"file": "shard-00000.npz", "sha256": sha, "count": pairs}],
    }
    write_manifest(out, manifest | ({"settings": settings} if settings else {}))
    return out


@pytest.mark.parametrize("task", ["box_stacking", "cloth_folding", "rope_box", "tshirt_folding"])
def test_one_command_makes_a_model_that_serves_and_plans(task, tmp_path, capsys):
    data = record(task, tmp_path / "data")
    out = tmp_path / "model"
    assert main(["train", "model", "--data", str(data), "--out", str(out), "--json", *TINY]) == 0
    printed = capsys.readouterr().out
    figures = json.loads(printed.strip().splitlines()[-1])
    for key in ("nodes", "edges", "epsilon", "known_training_images", "seconds", "mean_purity"):
        assert key in figures, key
    assert figures["task"] == task and figures["tuples"] == 40
    assert f"lsr up --model {out}" in printed
    # What lsr up reads: every part sealed, the task and the data's image size.
    info = ModelInfo.read(out, require_sealed=True)
    assert (info.task, info.image_size) == (task, 32)
    assert not (tmp_path / "model.partial").exists()
    recipe = json.loads((out / "recipe.json").read_text())
    assert recipe["figures"]["nodes"] == figures["nodes"]
    # The APN head follows the action kind: cells classified, pixels regressed.
    head = json.loads((out / "apn" / "config.json").read_text())["train"]["head"]
    assert head == ("hybrid" if get_task(task).spec.action.pixels else "classify")
    # A training image plans to itself through the folder as written.
    png = tmp_path / "start.png"
    png.write_bytes(encode_png(load_dataset(data).image1[0]))
    args = ["--start-image", str(png), "--goal-image", str(png)]
    assert main(["plan", "--model", str(out), "--out", str(tmp_path / "plans"), *args]) == 0


def test_a_failed_roadmap_keeps_the_trained_vae_and_says_how_to_go_on(tmp_path, capsys):
    data = record("box_stacking", tmp_path / "data")
    out = tmp_path / "model"
    flags = [*TINY[:6], "--min-samples", "10000"]  # every region pruned: no roadmap
    assert main(["train", "model", "--data", str(data), "--out", str(out), *flags]) != 0
    printed = capsys.readouterr()
    kept = tmp_path / "model.partial" / "vae"
    assert (kept / "vae.safetensors").is_file() and not out.exists()
    assert f"--vae {kept}" in printed.out
    assert "no nodes" in printed.err
    # going on from the kept VAE: its roadmap and APN only
    flags = [*TINY[2:], "--vae", str(kept)]
    weights = (kept / "vae.safetensors").read_bytes()
    assert main(["train", "model", "--data", str(data), "--out", str(out), *flags]) == 0
    said = capsys.readouterr()
    assert f"trained before: {kept}" in said.out and "vae steps" not in said.out
    assert json.loads((out / "recipe.json").read_text())["vae"] == str(kept)
    assert (out / "vae" / "vae.safetensors").read_bytes() == weights
    assert not kept.exists()  # the partial folder became the model


def test_a_vae_of_another_task_is_not_reused(tmp_path, capsys):
    out = tmp_path / "model"
    assert main(["train", "model", "--data", str(record("rope_box", tmp_path / "rope")),
                 "--out", str(out), *TINY]) == 0  # fmt: skip
    data = record("box_stacking", tmp_path / "box")
    args = ["--data", str(data), "--out", str(tmp_path / "other"), "--vae", str(out / "vae")]
    assert main(["train", "model", *args, *TINY]) != 0
    assert "trained on rope_box at 32 px, the dataset is box_stacking" in capsys.readouterr().err
    assert not (tmp_path / "other").exists()


def test_a_collapsed_vae_is_named_and_nothing_kept():
    from services.recipe import CollapsedVAEError, check_spread

    check_spread({"action_mean": 22.9, "noaction_mean": 0.44}, "l1")
    check_spread({"action_mean": 0.05, "noaction_mean": 0.04}, "none")  # no action term
    with pytest.raises(CollapsedVAEError, match=r"collapsed: action pairs lie 0\.05 apart"):
        check_spread({"action_mean": 0.05, "noaction_mean": 0.04}, "l1")


def test_build_roadmap_chooses_as_train_model_does(tmp_path, capsys):
    data = record("rope_box", tmp_path / "data")
    out = tmp_path / "model"
    assert main(["train", "model", "--data", str(data), "--out", str(out), *TINY]) == 0
    capsys.readouterr()
    roadmap = tmp_path / "roadmap"
    args = ["--vae", str(out / "vae"), "--data", str(data), "--out", str(roadmap)]
    assert main(["build-roadmap", *args]) == 0
    said = capsys.readouterr()
    assert "epsilon rule paper: measured for rope_box" in said.err and "w_eps 4.0" in said.err
    assert "keep_rare False: measured for rope_box" in said.err
    assert json.loads(said.out.strip().splitlines()[-1])["eps_rule"] == "paper"


def test_settings_come_from_the_dataset_and_say_why(tmp_path):
    declared = record("cloth_folding", tmp_path / "d", settings={"w_eps": 0.8, "min_samples": 6})
    vae, roadmap, apn, why = choose(load_dataset(declared), Recipe())
    assert (roadmap.w_eps, roadmap.min_samples) == (0.8, 6)
    assert "w_eps 0.8: the dataset's task.json settings" in why
    assert vae.steps == vae_steps(40) and apn.restarts == Recipe().apn_restarts
    _, roadmap, _, why = choose(load_dataset(declared), Recipe(min_samples=2))
    assert roadmap.min_samples == 2 and "min_samples 2: given" in why
    assert not vae.augment and not any(line.startswith("augment") for line in why)
    vae, _, _, why = choose(load_dataset(declared), Recipe(augment=True))
    assert vae.augment and any(line.startswith("augment: ") for line in why)
    vae, _, _, why = choose(load_dataset(declared), Recipe(vae=tmp_path / "v"))
    assert vae is None and f"vae {tmp_path / 'v'}: given, trained before (metric l1)" in why


def test_a_task_measured_settings_come_after_the_dataset_s(tmp_path):
    _, roadmap, _, why = choose(load_dataset(record("rope_box", tmp_path / "a")), Recipe())
    assert (roadmap.eps_rule, roadmap.w_eps) == ("paper", 4.0)
    assert "w_eps 4.0: measured for rope_box (docs/tasks)" in why
    declared = record("rope_box", tmp_path / "b", settings={"w_eps": 2.0})
    _, roadmap, _, why = choose(load_dataset(declared), Recipe(eps_rule="stable"))
    assert (roadmap.eps_rule, roadmap.w_eps) == ("stable", 2.0)
    _, roadmap, _, _ = choose(load_dataset(record("box_stacking", tmp_path / "c")), Recipe())
    assert (roadmap.eps_rule, roadmap.w_eps) == ("stable", 1.0)


def test_steps_grow_with_large_data_only():
    assert vae_steps(40) == vae_steps(1000) == 2400
    assert vae_steps(5000) == 2400  # 30 epochs of 5000 at 64 a batch: 2370
    assert vae_steps(10000) == 30 * 157


def _few_actions(tmp_path):
    data = record("box_stacking", tmp_path / "d", pairs=12)  # 8 action pairs
    return data, "8 action pairs; a model needs at least 10"


def _one_state(tmp_path):
    data = record("box_stacking", tmp_path / "d", pairs=40)
    arrays = dict(np.load(data / "shard-00000.npz"))
    arrays["state2"] = arrays["state1"] = np.repeat(arrays["state1"][:1], 40, axis=0)
    _rewrite(data, arrays)
    return data, "every image shows one state"


def _odd_size(tmp_path):
    data = record("box_stacking", tmp_path / "d", pairs=40, size=24)
    return data, "image_size must be a power of two"


def _no_still(tmp_path):
    data = record("box_stacking", tmp_path / "d", pairs=40)
    arrays = dict(np.load(data / "shard-00000.npz"))
    keep = arrays["a"] == 1
    _rewrite(data, {k: v[keep] for k, v in arrays.items()})
    return data, "0 no-action pairs"


def _rewrite(data, arrays):
    manifest = json.loads((data / "manifest.json").read_text())
    spec = get_task(manifest["task"]).spec
    manifest["shards"][0]["sha256"] = write_shard(data / "shard-00000.npz", arrays, spec)
    manifest["shards"][0]["count"] = len(arrays["a"])
    write_manifest(data, manifest)


@pytest.mark.parametrize("make", [_few_actions, _one_state, _odd_size, _no_still])
def test_a_dataset_it_cannot_train_from_writes_nothing(make, tmp_path, capsys):
    data, message = make(tmp_path)
    out = tmp_path / "model"
    assert main(["train", "model", "--data", str(data), "--out", str(out), *TINY]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists() and not (tmp_path / "model.partial").exists()


def test_a_model_is_never_trained_over_another(tmp_path, capsys):
    out = tmp_path / "model"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    data = record("box_stacking", tmp_path / "d")
    assert main(["train", "model", "--data", str(data), "--out", str(out), *TINY]) == 2
    assert "not empty" in capsys.readouterr().err
    assert (out / "keep.txt").read_text() == "mine"
