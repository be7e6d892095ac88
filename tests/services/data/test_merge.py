import json

import numpy as np
import pytest

from services.cli import main
from services.data.experience import ExperienceLog
from services.data.importer import ImportConfig, import_dataset
from services.data.merge import merge_datasets
from shared.dataset import DatasetError, load_dataset

from .conftest import write_recorded


@pytest.fixture
def imported(tmp_path):
    """Two imports of one recorded task (train and test splits of each)."""
    recorded = write_recorded(tmp_path / "recorded")
    import_dataset(ImportConfig(recorded, tmp_path / "one"), progress=False)
    import_dataset(ImportConfig(recorded, tmp_path / "two", seed=1), progress=False)
    return tmp_path / "one" / "train", tmp_path / "two" / "train"


def test_merged_tuples_are_the_sources_in_order_episodes_kept_apart(imported, tmp_path):
    first, second = imported
    merge_datasets([first, second], tmp_path / "merged")
    a, b, merged = load_dataset(first), load_dataset(second), load_dataset(tmp_path / "merged")
    assert len(merged) == len(a) + len(b)
    assert np.array_equal(merged.image1, np.concatenate([a.image1, b.image1]))
    assert np.array_equal(merged.u, np.concatenate([a.u, b.u]))
    names = merged.manifest["episodes"]
    episode_names = [names[e] for e in merged.episode]
    assert episode_names[: len(a)] == ["0/" + a.manifest["episodes"][e] for e in a.episode]
    assert episode_names[len(a) :] == ["1/" + b.manifest["episodes"][e] for e in b.episode]
    counts = merged.manifest["counts"]
    assert counts["action_pairs"] == int(merged.a.sum())
    assert [m["counts"]["tuples"] for m in merged.manifest["merged_from"]] == [len(a), len(b)]
    assert merged.manifest["settings"] == a.manifest["settings"]  # the first one's look


def test_experience_merges_with_its_recording(imported, tmp_path):
    first, _ = imported
    data = load_dataset(first)
    log = ExperienceLog(tmp_path / "exp", data.spec, data.image_size, source="explore")
    log.append(data.image2[:3], data.image1[:3], data.u[:3], data.state2[:3], data.state1[:3])
    assert main(["data", "merge", "--data", str(first), "--data", str(tmp_path / "exp"),
                 "--out", str(tmp_path / "merged")]) == 0  # fmt: skip
    merged = load_dataset(tmp_path / "merged")
    assert len(merged) == len(data) + 3 and merged.episode is None  # experience names none
    assert "experience" not in merged.manifest  # a dataset: experience is never appended to it
    assert merged.manifest["merged_from"][1]["experience"] == {"source": "explore"}


def test_what_cannot_merge_is_refused_and_nothing_written(imported, tmp_path):
    first, second = imported
    out = tmp_path / "merged"
    with pytest.raises(DatasetError, match="two or more"):
        merge_datasets([first], out)
    with pytest.raises(DatasetError, match="given twice"):
        merge_datasets([first, first], out)
    with pytest.raises(DatasetError, match="is one of the datasets"):
        merge_datasets([first, second], second, overwrite=True)
    manifest = json.loads((second / "manifest.json").read_text())
    manifest["image_size"] = 64
    other = tmp_path / "other"
    other.mkdir()
    for shard in second.iterdir():
        (other / shard.name).write_bytes(shard.read_bytes())
    (other / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(DatasetError, match="64 px"):
        merge_datasets([first, other], out)
    assert not out.exists() and not list(tmp_path.glob(".merged*"))
    assert len(load_dataset(second)) == manifest["counts"]["tuples"]  # sources untouched
