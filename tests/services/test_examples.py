"""Every script in examples/ runs as a user runs it: a child process, against the real stack
(one, shared, serving the shipped box model) or the tiny model, and does what it says."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from services.sim.explore import ExploreConfig, explore
from services.stack import Stack, StackConfig, free_port
from shared.dataset import load_dataset, read_manifest
from shared.tasks import get_task

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"
BOX = get_task("box_stacking")
START = {"stacks": [["red", "green"], ["blue"], ["yellow"]]}  # the examples' own
GOAL = {"stacks": [[], ["yellow", "green", "red"], ["blue"]]}
STEP = re.compile(r"^\s+\d+\. (\{.*\})$")


def run(script: str, *args: str, timeout: float = 120) -> str:
    done = subprocess.run(
        [sys.executable, str(EXAMPLES / script), *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    assert done.returncode == 0, f"{script} failed:\n{done.stdout}\n{done.stderr}"
    return done.stdout


def plans_in(output: str) -> list[list[dict]]:
    """The actions each printed plan lists, in order."""
    plans: list[list[dict]] = []
    for line in output.splitlines():
        if line.startswith(("plan ", "[")) and "actions" in line:
            plans.append([])
        elif match := STEP.match(line):
            plans[-1].append(json.loads(match.group(1)))
    return plans


def assert_leads_from_start_to_goal(actions: list[dict]) -> None:
    state = BOX.parse_state(START)
    for action in actions:
        state = BOX.apply(state, BOX.parse_action(action))  # raises on an illegal move
    assert state == BOX.parse_state(GOAL)


def test_every_example_is_listed_in_the_catalogue_and_tested_here():
    scripts = sorted(p.name for p in EXAMPLES.glob("*.py"))
    catalogue = (EXAMPLES / "README.md").read_text()
    tests = Path(__file__).read_text()
    assert scripts == ["grow_roadmap.py", "import_recorded.py", "plan_rest.py", "robot_zenoh.py"]
    for name in scripts:
        assert f"({name})" in catalogue, f"examples/README.md does not link {name}"
        assert f'run("{name}"' in tests, f"no test runs {name}"


@pytest.fixture(scope="module")
def stack(tmp_path_factory, patient):
    config = StackConfig(
        port=free_port(),
        zenoh_port=free_port(),
        models=(ROOT / "models" / "box_stacking",),
        log_dir=tmp_path_factory.mktemp("examples-stack"),
        env=patient,
    )
    with Stack(config) as running:
        running.start()
        running.wait_healthy(90)
        yield running


def test_plan_rest_prints_legal_plans_and_writes_their_images(stack, tmp_path):
    output = run("plan_rest.py", "--url", stack.config.url, "--out", str(tmp_path))
    plans = plans_in(output)
    assert 1 <= len(plans) <= 2
    for k, actions in enumerate(plans):
        assert_leads_from_start_to_goal(actions)
        images = sorted(tmp_path.glob(f"plan{k}_*.png"))
        assert len(images) == len(actions) + 1  # start, then after each action
        assert Image.open(images[0]).size == (64, 64)


def test_robot_zenoh_takes_its_plan_from_its_own_key(stack):
    output = run("robot_zenoh.py", "--connect", stack.config.endpoint, "--robot-id", "arm-7")
    assert output.startswith("[arm-7] plan ")
    (actions,) = plans_in(output)
    assert_leads_from_start_to_goal(actions)


@pytest.mark.parametrize("page", ["README.md", "docs/serving/rest.md", "docs/serving/zenoh.md"])
def test_the_python_snippets_of_the_front_page_and_the_docs_run_as_shown(stack, page):
    snippets = re.findall(r"```python\n(.*?)```", (ROOT / page).read_text(), re.S)
    assert snippets
    for code in snippets:  # as written, but against this stack's ports
        code = code.replace("127.0.0.1:8000", f"127.0.0.1:{stack.config.port}")
        code = code.replace("tcp/127.0.0.1:7447", stack.config.endpoint)
        done = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT
        )
        assert done.returncode == 0, f"{page}:\n{code}\n{done.stderr}"
        assert '"pick"' in done.stdout or "'pick'" in done.stdout  # it printed an action


def recording(folder: Path, episodes: int = 5, frames: int = 4) -> int:
    """A robot's recording: frames of 80 px (the import resizes) and a log; tuples made."""
    rng = np.random.default_rng(0)
    lines = []
    for episode in range(episodes):
        for i in range(frames):
            name = f"cam/{episode}_{i}.png"
            (folder / name).parent.mkdir(parents=True, exist_ok=True)
            Image.fromarray(rng.integers(0, 256, (80, 80, 3), np.uint8)).save(folder / name)
            action = {"pick": {"row": int(rng.integers(256)), "col": 7}, "grip": "firm"}
            lines.append({"frame": name, "action": action if i % 3 else None, "episode": episode})
    (folder / "log.jsonl").write_text("".join(json.dumps(line) + "\n" for line in lines))
    return episodes * (frames - 1)


def test_import_recorded_makes_a_dataset_of_consecutive_frames(tmp_path):
    source = tmp_path / "rec"
    tuples = recording(source)
    out = tmp_path / "data"
    report = json.loads(run("import_recorded.py", "--recording", str(source), "--out", str(out)))
    assert report["task"] == "towel" and report["rows"] == tuples
    train, test = load_dataset(out / "train"), load_dataset(out / "test")
    assert len(train) + len(test) == tuples and len(test) > 0
    assert train.image1.shape[1:] == (64, 64, 3)
    assert read_manifest(out / "train")["spec"]["state"] is None  # no states: a data-only task
    assert int(train.a.sum() + test.a.sum()) == report["action_pairs"] == 2 * 5  # i = 1, 2


def test_grow_roadmap_makes_a_new_version_from_recorded_experience(tiny_model, tmp_path):
    explored, model = tmp_path / "explored", tmp_path / "model"
    shutil.copytree(tiny_model[0], explored)
    shutil.copytree(tiny_model[0], model)
    experience = tmp_path / "experience"
    # the simulator's experience, recorded: the first seed whose 20 tries record some (the tiny
    # model's proposals are mostly refused, and an explorer's choices change what each draws)
    for seed in range(10):
        cfg = ExploreConfig(actions=20, seed=seed, grow_every=10, chain=2, seen_share=0.8)
        if explore(explored, cfg, experience, progress=False)["recorded"]:
            break
    output = run("grow_roadmap.py", "--model", str(model), "--experience", str(experience))
    report = json.loads(output.splitlines()[0])
    assert report["version"] == "v2"
    assert report["tuples"] == len(load_dataset(experience)) > 0
    assert output.splitlines()[1] == "versions ['v1', 'v2'], current v2"
