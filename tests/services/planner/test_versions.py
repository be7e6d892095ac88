"""Roadmap versions: pruning keeps v1, the current one and the newest."""

import json

import pytest

from services.cli import main
from services.planner import versions


def model_with_versions(root, grown, current):
    (root / "roadmap").mkdir(parents=True)
    for name in grown:
        (root / "roadmap" / "versions" / name).mkdir(parents=True)
        (root / "roadmap" / "versions" / name / "roadmap.json").write_text("{}")
    versions.make_current(root, current)
    return root


def test_pruning_keeps_v1_the_current_version_and_the_newest(tmp_path, capsys):
    model = model_with_versions(tmp_path / "m", ["v2", "v3", "v4", "v5"], current="v3")
    assert versions.prune(model, keep=1) == ["v2", "v4"]
    assert versions.versions(model) == ["v1", "v3", "v5"]
    assert versions.current_version(model) == "v3"
    assert versions.prune(model, keep=0) == []  # v5 stays: its name is never given again
    assert versions.next_version(model) == "v6"
    assert not list((model / "roadmap" / "versions").glob(".*"))  # nothing left half-deleted
    assert main(["roadmap", "versions", "--model", str(model), "--use", "v5", "--keep", "0"]) == 0
    shown = json.loads(capsys.readouterr().out)
    assert shown == {"current": "v5", "versions": ["v1", "v5"], "deleted": ["v3"]}
    with pytest.raises(ValueError, match="keep"):
        versions.prune(model, keep=-1)
