import json
import subprocess
import sys
from pathlib import Path

import pytest

from services.cli import build_parser, main
from shared.dataset import load_dataset


def run_lsr(*args):
    return subprocess.run(
        [sys.executable, "-m", "services.cli", *args], capture_output=True, text=True, timeout=120
    )


def test_task_info_prints_json():
    proc = run_lsr("task", "info", "box_stacking")
    assert proc.returncode == 0, proc.stderr
    info = json.loads(proc.stdout)
    assert info["num_states"] == 288 and len(info["boxes"]) == 4


def test_data_generate(tmp_path):
    out = tmp_path / "data"
    proc = run_lsr(
        "data",
        "generate",
        "--task",
        "box_stacking",
        "--pairs",
        "6",
        "--seed",
        "1",
        "--size",
        "32",
        "--workers",
        "1",
        "--out",
        str(out),
    )
    assert proc.returncode == 0, proc.stderr
    data = load_dataset(out)
    assert len(data) == 6 and data.image_size == 32 and data.image1.shape[1:] == (32, 32, 3)


def test_render_rejects_an_invalid_state_clearly(tmp_path, capsys):
    rc = main(
        [
            "render",
            "--state",
            '{"stacks": [["red"], ["red"], []]}',
            "--out",
            str(tmp_path / "x.png"),
        ]
    )
    assert rc == 2
    assert "appears twice" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()


def test_cloth_task_info_and_invalid_cloth_states(tmp_path, capsys):
    proc = run_lsr("task", "info", "cloth_folding")
    assert proc.returncode == 0, proc.stderr
    info = json.loads(proc.stdout)
    assert info["num_states"] == 16 and info["image_frame"] == 256
    out = tmp_path / "x.png"
    for state, message in (
        ('{"folds": ["top_left", "top_left"]}', "state.folds[1]: fold 'top_left' appears twice"),
        ('{"folds": ["middle"]}', "state.folds[0]: unknown fold 'middle'"),
        ('{"stacks": [["red"], [], []]}', "'folds' list (got keys ['stacks'])"),
    ):
        rc = main(["render", "--task", "cloth_folding", "--state", state, "--out", str(out)])
        assert rc == 2 and message in capsys.readouterr().err
    assert not out.exists()


def test_demo_writes_a_png(tmp_path):
    out = tmp_path / "demo.png"
    assert main(["demo", "--out", str(out), "--size", "48"]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_robot_refuses_an_id_that_is_not_one_key_chunk(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["robot", "--robot-id", "arm/7", "--start-state", "{}", "--goal-state", "{}"])
    assert exit_info.value.code == 2
    assert "not one zenoh key chunk" in capsys.readouterr().err


@pytest.mark.parametrize(
    "command", [["plan", "--out", "plans"], ["eval", "system"]], ids=["plan", "eval system"]
)
def test_the_default_model_is_found_from_any_working_directory(command, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # not the repository's root: no models/ here
    model = build_parser().parse_args(command).model
    assert model.is_absolute()
    assert model == Path(__file__).resolve().parents[2] / "models" / "box_stacking"
    assert all((model / part).is_dir() for part in ("vae", "roadmap", "apn"))


def test_eval_system_prints_table_three_for_the_shipped_model(capsys):
    model = Path(__file__).resolve().parents[2] / "models" / "box_stacking"
    assert main(["eval", "system", "--model", str(model), "--pairs", "3", "--json"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["pairs"] == 3 and result["success"] == 100.0
    assert result["appearance"] == "camera"  # the shipped model's training data's
    assert result["table3"] == {
        "system": 100.0,
        "transitions": 100.0,
        "transitions_as_seen": 100.0,
        "vfm": 100.0,
        "apn": 100.0,
    }


def test_render_takes_an_appearance_level(tmp_path, capsys):
    import numpy as np
    from PIL import Image

    state = '{"stacks": [["red"], ["green", "blue"], ["yellow"]]}'
    images = {}
    for level in ("clean", "camera"):
        out = tmp_path / f"{level}.png"
        assert main(["render", "--state", state, "--appearance", level, "--out", str(out)]) == 0
        images[level] = np.asarray(Image.open(out))
    assert not np.array_equal(images["clean"], images["camera"])
    with pytest.raises(SystemExit) as exit_info:
        main(["render", "--state", state, "--appearance", "foggy", "--out", str(out)])
    assert exit_info.value.code == 2
    assert "--appearance: invalid choice: 'foggy'" in capsys.readouterr().err
