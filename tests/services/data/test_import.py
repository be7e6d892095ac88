"""lsr data import / export: the checks before writing, the split, the lossless round trip."""

import csv
import json

import numpy as np
import pytest
from PIL import Image

from services.cli import main
from services.data.exporter import export_dataset
from services.data.importer import ImportConfig, import_dataset
from services.data.pairs import DataImportError
from services.sim.workcell import FRAME_SIZE
from shared.dataset import load_dataset, read_manifest
from shared.tasks.declared import DataTask


def rows(root):
    return [json.loads(line) for line in (root / "pairs.jsonl").read_text().splitlines()]


def write_rows(root, lines):
    (root / "pairs.jsonl").write_text("".join(json.dumps(x) + "\n" for x in lines))


def test_import_writes_train_and_test_split_by_episode(recorded, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["data", "import", "--from", str(recorded), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "resized 144 of 144 images to 32 px; 28 not square were centre-cropped" in printed
    result = json.loads(printed.strip().splitlines()[-1])
    assert result["rows"] == 72 and result["episodes"] == 12
    train, test = load_dataset(out / "train"), load_dataset(out / "test")
    assert len(train) + len(test) == 72 and len(test) == 12  # 2 of 12 episodes, 6 pairs each
    names = [set(np.array(read_manifest(out / s)["episodes"])) for s in ("train", "test")]
    assert not names[0] & names[1]  # no episode on both sides
    assert train.spec.state is None and train.spec.task == "square_moving"
    assert train.image1.shape[1:] == (32, 32, 3) and train.u.dtype == np.int8
    assert read_manifest(out / "train")["settings"] == {"w_eps": 1.0, "min_samples": 1}
    # The actions are the declared fields: the category is stored as its index.
    task = DataTask(train.spec)
    first = next(i for i in range(len(train)) if train.a[i])
    action = task.action_to_json(task.array_to_action(train.u[first]))
    assert set(action) == {"pick", "release", "grip"} and action["grip"] in ("soft", "firm")
    assert (train.u[train.a == 0] == -1).all()
    # Another seed holds out other episodes.
    again = tmp_path / "again"
    import_dataset(ImportConfig(recorded, again, seed=1), progress=False)
    assert read_manifest(again / "test")["episodes"] != read_manifest(out / "test")["episodes"]


def test_a_wide_image_is_centre_cropped_not_stretched(recorded, tmp_path):
    out = tmp_path / "out"
    import_dataset(ImportConfig(recorded, out, test_fraction=0), progress=False)
    data = load_dataset(out / "train")
    line = rows(recorded)[2]  # frame 5 (64 x 48) is image1 of the third row
    assert Image.open(recorded / line["image1"]).size == (64, 48)
    image = data.image1[2].astype(int)
    # The square stays square: as many bright columns as rows.
    bright = (image > 220).all(-1)
    assert abs(int(bright.any(0).sum()) - int(bright.any(1).sum())) <= 1


def test_csv_pairs_import_like_jsonl(recorded, tmp_path):
    lines = rows(recorded)
    (recorded / "pairs.jsonl").unlink()
    with (recorded / "pairs.csv").open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["image1", "image2", "action", "episode"])
        for x in lines:
            action = "" if x["action"] is None else json.dumps(x["action"])
            writer.writerow([x["image1"], x["image2"], action, x["episode"]])
    import_dataset(ImportConfig(recorded, tmp_path / "csv"), progress=False)
    assert len(load_dataset(tmp_path / "csv" / "train")) == 60


def test_export_then_import_is_lossless(recorded, tmp_path):
    first = tmp_path / "first"
    import_dataset(ImportConfig(recorded, first), progress=False)
    exported = tmp_path / "exported"
    result = export_dataset([first / "train", first / "test"], exported, progress=False)
    assert result["splits"] == {"train": 60, "test": 12} and not result["states_dropped"]
    assert json.loads((exported / "task.json").read_text())["action"][4] == {
        "name": "grip",
        "categories": ["soft", "firm"],
    }
    second = tmp_path / "second"
    import_dataset(ImportConfig(exported, second, seed=99), progress=False)  # its split column
    for split in ("train", "test"):
        a, b = load_dataset(first / split), load_dataset(second / split)
        for field in ("image1", "image2", "a", "u", "episode"):
            assert np.array_equal(getattr(a, field), getattr(b, field)), (split, field)
        ma, mb = read_manifest(first / split), read_manifest(second / split)
        assert ma["episodes"] == mb["episodes"] and ma["spec"] == mb["spec"]
        assert ma["settings"] == mb["settings"]
    again = tmp_path / "again"
    export_dataset([second / "train", second / "test"], again, progress=False)
    assert (again / "pairs.jsonl").read_bytes() == (exported / "pairs.jsonl").read_bytes()


def test_a_float_field_round_trips_at_its_levels(recorded, tmp_path):
    task = json.loads((recorded / "task.json").read_text())
    task["action"].append({"name": "force", "float": [0.0, 2.0], "levels": 5})
    (recorded / "task.json").write_text(json.dumps(task))
    lines = rows(recorded)
    for x in lines:
        if x["action"] is not None:
            x["action"]["force"] = 0.5
    write_rows(recorded, lines)
    out = tmp_path / "out"
    import_dataset(ImportConfig(recorded, out), progress=False)
    data = load_dataset(out / "train")
    spec_task = DataTask(data.spec)
    act = spec_task.array_to_action(data.u[data.a == 1][0])
    assert spec_task.action_to_json(act)["force"] == 0.5


# --- refusals: each names the file and line, and leaves nothing behind -------------------------


def refuse(recorded, tmp_path, match, name=None):
    out = tmp_path / "out"
    with pytest.raises((DataImportError, ValueError), match=match):
        import_dataset(ImportConfig(recorded, out, name=name), progress=False)
    assert not out.exists()
    assert not (tmp_path / ".out.partial").exists()


def test_missing_image_is_refused(recorded, tmp_path):
    (recorded / rows(recorded)[3]["image2"]).unlink()
    refuse(recorded, tmp_path, r"pairs\.jsonl:4: image2: img.*frame0008\.png does not exist")


def test_unreadable_image_is_refused(recorded, tmp_path):
    (recorded / rows(recorded)[1]["image1"]).write_bytes(b"\x89PNG\r\n\x1a\n not really")
    refuse(recorded, tmp_path, r"pairs\.jsonl:2: image1: .*not a readable PNG or JPEG")


def test_image_not_rgb_convertible_is_refused(recorded, tmp_path):
    path = recorded / rows(recorded)[5]["image1"]
    rgba = np.zeros((48, 48, 4), np.uint8)  # fully transparent
    Image.fromarray(rgba, "RGBA").save(path)
    refuse(recorded, tmp_path, r"pairs\.jsonl:6: image1: .*transparent pixels")


def test_missing_field_is_refused(recorded, tmp_path):
    lines = rows(recorded)
    del lines[4]["action"]["release"]["col"]
    write_rows(recorded, lines)
    refuse(recorded, tmp_path, r"pairs\.jsonl:5: action: release\.col: missing")


def test_field_out_of_range_is_refused(recorded, tmp_path):
    lines = rows(recorded)
    lines[6]["action"]["pick"]["row"] = 48
    write_rows(recorded, lines)
    refuse(recorded, tmp_path, r"pairs\.jsonl:7: action: pick\.row: 48 is out of range 0\.\.47")


def test_unknown_category_is_refused(recorded, tmp_path):
    lines = rows(recorded)
    lines[0]["action"]["grip"] = "hard"
    write_rows(recorded, lines)
    refuse(recorded, tmp_path, r"pairs\.jsonl:1: action: grip: expected one of \['soft', 'firm'\]")


def test_duplicate_line_is_refused(recorded, tmp_path):
    lines = rows(recorded)
    write_rows(recorded, [*lines[:10], lines[3], *lines[10:]])
    refuse(recorded, tmp_path, r"pairs\.jsonl:11: duplicate of line 4")


def test_builtin_task_name_is_refused(recorded, tmp_path):
    refuse(recorded, tmp_path, r"task\.json: name 'cloth_folding' clashes with a built-in task "
           r".* whose actions differ", name="cloth_folding")  # fmt: skip


def test_every_file_is_checked_before_the_name(recorded, tmp_path):
    (recorded / "img" / "frame0008.png").unlink()
    refuse(recorded, tmp_path, r"pairs\.jsonl:4: image2: .*frame0008\.png does not exist",
           name="cloth_folding")  # fmt: skip


def test_a_builtin_tasks_export_imports_as_that_task_without_flags(tiny_model, tmp_path):
    _, data = tiny_model
    exported = tmp_path / "exported"
    export_dataset([data], exported, progress=False)
    assert json.loads((exported / "task.json").read_text())["name"] == "box_stacking"
    out = tmp_path / "out"
    assert import_dataset(ImportConfig(exported, out), progress=False)["task"] == "box_stacking"
    back, original = load_dataset(out / "train"), load_dataset(data)
    assert back.task == "box_stacking" and back.spec.state is None  # export drops states
    for field in ("image1", "image2", "a", "u"):
        assert np.array_equal(getattr(back, field), getattr(original, field)), field


def test_bad_task_json_is_refused(recorded, tmp_path):
    task = json.loads((recorded / "task.json").read_text())
    task["action"][1]["range"] = [0, 48]  # a pixel beyond the 48 px frame
    (recorded / "task.json").write_text(json.dumps(task))
    refuse(recorded, tmp_path, r"task\.json: action\[1\] \(pick\.col\): a pixel range must lie")


def test_an_export_of_test_data_alone_imports_as_test_data(recorded, tmp_path):
    first = tmp_path / "first"
    import_dataset(ImportConfig(recorded, first), progress=False)
    exported = tmp_path / "exported"
    export_dataset([first / "test"], exported, progress=False)
    second = tmp_path / "second"
    result = import_dataset(ImportConfig(exported, second), progress=False)
    assert list(result["splits"]) == ["test"] and not (second / "train").exists()
    a, b = load_dataset(first / "test"), load_dataset(second / "test")
    assert np.array_equal(a.image1, b.image1) and np.array_equal(a.u, b.u)


def test_an_episode_in_both_splits_is_refused(recorded, tmp_path):
    lines = rows(recorded)
    for i, x in enumerate(lines):
        x["split"] = "test" if i == 1 else "train"
    write_rows(recorded, lines)
    refuse(recorded, tmp_path, r"episode 'ep0' has rows in both train and test")


def test_split_on_some_rows_only_is_refused(recorded, tmp_path):
    lines = rows(recorded)
    lines[7]["split"] = "test"
    write_rows(recorded, lines)
    refuse(recorded, tmp_path, r"pairs\.jsonl:8: split: given on some rows and not on others")


def test_image_outside_the_folder_is_refused(recorded, tmp_path):
    lines = rows(recorded)
    lines[2]["image1"] = "../elsewhere.png"
    write_rows(recorded, lines)
    refuse(recorded, tmp_path, r"pairs\.jsonl:3: image1: '\.\./elsewhere\.png' is not inside")


def test_an_existing_output_is_kept(recorded, tmp_path):
    out = tmp_path / "out"
    (out / "train").mkdir(parents=True)
    (out / "train" / "keep.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="--overwrite"):
        import_dataset(ImportConfig(recorded, out), progress=False)
    assert (out / "train" / "keep.txt").read_text() == "mine"


def test_a_large_jpeg_is_scaled_and_counted(recorded, tmp_path):
    lines = rows(recorded)
    big = np.zeros((256, 320, 3), np.uint8) + np.array([200, 60, 60], np.uint8)
    big[32:96, 32 + 32 : 96 + 32] = 255  # the square of state 0, at 256 / 48 times the size
    Image.fromarray(big).save(recorded / "big.jpg", quality=95)
    lines[0]["image1"] = "big.jpg"
    write_rows(recorded, lines)
    result = import_dataset(ImportConfig(recorded, tmp_path / "out", test_fraction=0), False)
    assert result["image_sizes"]["320x256"] == 1 and result["cropped"] == 29
    image = load_dataset(tmp_path / "out" / "train").image1[0].astype(int)
    assert image.shape == (32, 32, 3)
    bright = (image > 220).all(-1)
    assert bright[4:12, 4:12].all() and not bright[20:, 20:].any()  # the square, top left


def _frames_folder(root, covered_row=None):
    """Camera frames of box-stacking states, markers round the view, under a declared task
    that carries the cell's markers."""
    from services.sim.worlds import make_world
    from shared.tasks import get_task

    from .conftest import TASK

    root.mkdir()
    workcell = get_task("box_stacking").workcell
    (root / "task.json").write_text(json.dumps({**TASK, "markers": workcell.to_json()}))
    lines, rng = [], np.random.default_rng(4)
    with make_world("box_stacking", 32, appearance="camera") as world:
        states = world.task.all_states()
        for i in range(4):
            world.reset(states[i * 7], rng)
            for k in (1, 2):
                frame = world.frame()
                if i == covered_row and k == 2:
                    frame[FRAME_SIZE // 2 :] = 128  # a hand over the near markers
                Image.fromarray(frame).save(root / f"f{i}{k}.png")
            lines.append(json.dumps({"image1": f"f{i}1.png", "image2": f"f{i}2.png",
                                     "action": None, "episode": f"e{i}"}))  # fmt: skip
    (root / "pairs.jsonl").write_text("\n".join(lines) + "\n")
    return root, workcell


def test_frames_are_registered_to_the_table_frame_with_task_json_s_markers(tmp_path):
    from services.runtime import declare_model_task
    from shared.registration import Registration
    from shared.tasks import get_task

    source, workcell = _frames_folder(tmp_path / "rec")
    config = ImportConfig(source=source, out=tmp_path / "out", name="framed", test_fraction=0)
    result = import_dataset(config, progress=False)
    assert result["registered"] == result["images"] and result["cropped"] == 0  # not cropped
    data = load_dataset(tmp_path / "out" / "train")
    assert data.image1.shape == (4, 32, 32, 3)
    assert data.manifest["markers"] == workcell.to_json()
    expected = Registration(workcell, 32).register(np.array(Image.open(source / "f01.png")))
    assert np.array_equal(data.image1[0], expected.image)
    declared = json.loads((tmp_path / "out" / "task.json").read_text())
    assert declared["markers"] == workcell.to_json()
    # a model of it serves the task with its markers: its encoder registers frames with them
    declare_model_task({"dataset": {"spec": data.manifest["spec"], "markers": declared["markers"]}})
    assert get_task("framed").workcell == workcell
    assert get_task("framed").info()["markers"] == workcell.to_json()


def test_a_frame_whose_markers_are_not_found_is_refused_naming_its_row(tmp_path):
    source, _ = _frames_folder(tmp_path / "rec", covered_row=2)
    with pytest.raises(DataImportError, match=r"1 image\(s\) could not be registered.*:3: "
                       r"image2: f22.png: the table markers were not found"):  # fmt: skip
        import_dataset(ImportConfig(source=source, out=tmp_path / "out"))
    assert not (tmp_path / "out").exists()


def test_bad_markers_in_task_json_are_refused(recorded, tmp_path):
    from .conftest import TASK

    (recorded / "task.json").write_text(json.dumps({**TASK, "markers": {"markers": "x"}}))
    refuse(recorded, tmp_path, "markers")
