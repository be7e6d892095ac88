"""`lsr build-roadmap`: encode a training set with a VAE and build its Latent Space Roadmap."""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from services.encoder.checkpoint import load_vae, read_vae_config
from services.planner.evaluate import NodeLabels, label_nodes
from services.planner.exits import action_classes, action_exits
from services.planner.knowing import FILE as MATCH_FILE
from services.planner.knowing import Calibration, calibrate, ratios, save_calibration
from services.planner.members import MEMBERS, Members, interleave
from services.planner.roadmap import ARRAYS_NAME, JSON_NAME, Roadmap, RoadmapConfig, build_roadmap
from services.planner.versions import CURRENT, FIRST, current_version, roadmap_dir
from shared.checkpoint import seal
from shared.dataset import load_dataset
from shared.tasks import declare_task, get_task

LABELS = "labels.json"


def default_metric(vae_config: dict[str, Any]) -> str:
    """The roadmap uses the metric the VAE was shaped with (L1 for the baseline)."""
    metric = vae_config["train"]["metric"]
    return "l1" if metric == "none" else metric


def calibrate_and_seal(roadmap: Roadmap, members: Members, folder: Path | str) -> Calibration:
    """What the roadmap knows, from every training image, written beside the roadmap with its
    members and sealed with it: build-roadmap and lsr calibrate."""
    calibration = calibrate(roadmap, members.points, members.errors)
    save_calibration(calibration, folder)
    members.save(Path(folder))
    seal(folder, [ARRAYS_NAME, JSON_NAME, MATCH_FILE, MEMBERS])
    return calibration


def build_from_dataset(
    vae_dir: Path | str, data_dir: Path | str, config: RoadmapConfig, out_dir: Path | str
) -> dict[str, Any]:
    started = time.perf_counter()
    if (Path(out_dir) / CURRENT).exists():  # a grown model would go on planning with a version
        raise ValueError(
            f"{out_dir}: holds grown roadmap versions ({CURRENT}, versions/); build into an "
            "empty folder, or move that one aside first"
        )
    data = load_dataset(data_dir)
    model, _ = load_vae(vae_dir)
    members = Members.encode(model, data)
    encoded = time.perf_counter()
    declared = declare_task(data.spec)
    config = replace(config, one_way=not declared.spec.undo)  # the APN knows no other way
    same = declared.same_action
    classes = action_classes(data.a, data.u, same)
    roadmap = build_roadmap(members.points[0::2], members.points[1::2], data.a, config, classes)
    # where each node's actions lead: memory for nodes that stand for look-alike states
    roadmap = replace(roadmap, exits=action_exits(roadmap.point_node, data.a, data.u, same))
    built = time.perf_counter()
    roadmap.save(out_dir)
    calibration = calibrate_and_seal(roadmap, members, out_dir)
    _, terms = ratios(roadmap, calibration, members.points, members.errors)
    purity: dict[str, Any] = {}
    if data.spec.state is not None:  # node labels need the states the data declares
        task = get_task(data.task)
        labels = label_nodes(
            roadmap.point_node, interleave(data.state1, data.state2), len(roadmap.nodes), task
        )
        (Path(out_dir) / LABELS).write_text(json.dumps(labels.to_json(task)) + "\n")
        purity = {
            "mean_purity": float(labels.purity.mean()) if len(labels.purity) else 0.0,
            "pure_nodes": int((labels.purity == 1).sum()),
        }
    return {
        "nodes": len(roadmap.nodes),
        "edges": len(roadmap.edges),
        "epsilon": roadmap.epsilon,
        **purity,
        "match_threshold": calibration.threshold,
        "known_training_images": float((terms.max(1) <= 1.0).mean()),  # every knowing term
        "encode_seconds": encoded - started,
        "build_seconds": built - encoded,
        "forbidden_turns": sum(map(len, roadmap.turns.values())),
        "one_way": config.one_way,
        "unshown_steps": len(roadmap.unshown),  # edges' directions no action pair took
        **{k: v for k, v in roadmap.stats.items() if not isinstance(v, dict)},
    }


def calibrate_model(model_dir: Path | str, data_dir: Path | str) -> dict[str, Any]:
    """Calibrate (or re-calibrate) a model's roadmap on its training data: `lsr calibrate`."""
    model_dir = Path(model_dir)
    data = load_dataset(data_dir)
    task = read_vae_config(model_dir / "vae")["dataset"]["task"]
    if data.task != task:
        raise ValueError(f"{data_dir} holds {data.task!r} data, the model plans {task!r}")
    if current_version(model_dir) != FIRST:
        raise ValueError(
            f"{model_dir}: its roadmap grew ({current_version(model_dir)}); a grown version is "
            "calibrated as it grows, on its training data and experience together"
        )
    folder = roadmap_dir(model_dir)
    roadmap = Roadmap.load(folder)
    model, _ = load_vae(model_dir / "vae")
    return calibrate_and_seal(roadmap, Members.encode(model, data), folder).to_json()


def load_labels(folder: Path | str, task_name: str) -> NodeLabels:
    path = Path(folder) / LABELS
    if not path.is_file():
        raise ValueError(f"{folder}: no {LABELS}; rebuild with lsr build-roadmap")
    return NodeLabels.from_json(get_task(task_name), json.loads(path.read_text()))


def load_model(model_dir: Path | str) -> tuple[Any, dict[str, Any], Roadmap, NodeLabels]:
    """A model folder: vae/ and roadmap/ side by side."""
    model_dir = Path(model_dir)
    vae, vae_config = load_vae(model_dir / "vae")
    folder = roadmap_dir(model_dir)
    roadmap = Roadmap.load(folder)
    labels = load_labels(folder, vae_config["dataset"]["task"])
    return vae, vae_config, roadmap, labels
