"""`lsr train model`: one dataset folder to a model folder that `lsr up` serves.

The step commands (`lsr train vae`, `lsr build-roadmap`, `lsr train apn`) leave every choice to
their flags; a robot's owner should not have to know them. Here each setting is chosen from the
dataset itself (its size, the task.json settings it declares, its action kind) and printed with
the reason, and a flag remains for each only for research. The model is trained into a folder
beside OUT and moved into place when it is whole, so that OUT never holds half a model.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from services.apn.train import APNTrainConfig, train_apn
from services.encoder.checkpoint import read_vae_config
from services.encoder.model import VAEConfig
from services.encoder.train import DEFAULT_STEPS, Metric, TrainConfig, train_vae
from services.planner.build import build_from_dataset
from services.planner.roadmap import EpsilonRule, RoadmapConfig
from shared.dataset import Dataset, DatasetError, load_dataset, publish
from shared.tasks import get_task
from shared.tasks.base import Task, TaskError

# The fewest tuples of each kind a model can be trained from: the APN keeps a fifth of the
# action pairs for validation, and epsilon is measured on the no-action pairs.
MIN_ACTION_PAIRS = 10
MIN_NO_ACTION_PAIRS = 2
# VAE steps: at least DEFAULT_STEPS (a small dataset needs as many updates as a large one), and
# at least this many passes over a large one (the shipped recipes' 30 epochs).
MIN_EPOCHS = 30
# APN runs from fresh weights, the lowest validation loss kept: one T-shirt run in five learned
# moves wrong and its validation loss said so; a run is seconds beside the VAE's minutes.
APN_RESTARTS = 5
# A VAE whose action pairs lie less than this many times farther apart than its no-action pairs
# has collapsed: rope-box data walked five moves from each reset gave 0.05 against 0.04 (healthy
# models here: 52 to 140 times) and a roadmap without nodes.
MIN_SPREAD = 2.0
RECORD = "recipe.json"  # what was chosen and the figures, beside the model


@dataclass(frozen=True)
class Recipe:
    """What `lsr train model` may be told; None everywhere means: chosen from the dataset."""

    metric: Metric = "l1"
    seed: int = 0
    device: str = "auto"
    vae_steps: int | None = None
    eps_rule: EpsilonRule | None = None
    w_eps: float | None = None
    min_samples: int | None = None
    apn_steps: int | None = None
    apn_restarts: int = APN_RESTARTS
    vae: Path | None = None  # a VAE trained on this dataset before: the roadmap and APN only
    augment: bool = False  # the VAE's encoder sees each image under a drawn look (issue 50)


class CollapsedVAEError(ValueError):
    """The VAE put action pairs about as close as no-action pairs: no roadmap can be built."""


def reuse_vae(vae_dir: Path, data: Dataset) -> dict[str, Any]:
    """The config of a VAE trained before, checked against the dataset it is to serve."""
    config = read_vae_config(vae_dir)
    trained = config.get("dataset", {})
    size = config["model"]["image_size"]
    if trained.get("task") != data.task or size != data.image_size:
        raise ValueError(
            f"{vae_dir}: trained on {trained.get('task')} at {size} px, the dataset is "
            f"{data.task} at {data.image_size} px"
        )
    return config


def check_spread(final: dict[str, Any], metric: str) -> None:
    """CollapsedVAEError where the action term lost (see MIN_SPREAD)."""
    moved, still = final.get("action_mean"), final.get("noaction_mean")
    if metric == "none" or moved is None or still is None:
        return
    if moved < MIN_SPREAD * still:
        raise CollapsedVAEError(
            f"the VAE collapsed: action pairs lie {moved:.3g} apart on average, no-action "
            f"pairs {still:.3g}, where the action term asks them apart; nothing is kept: "
            "train again with another --seed"
        )


def check_trainable(data: Dataset, where: Path | str) -> None:
    """DatasetError naming what makes a dataset unfit to train a model from."""
    size = data.image_size
    shapes = {data.image1.shape[1:], data.image2.shape[1:]}
    if shapes != {(size, size, 3)}:
        found = ", ".join("x".join(map(str, s)) for s in sorted(shapes))
        raise DatasetError(
            f"{where}: images must be {size} x {size} x 3 as the manifest says, got {found}"
        )
    try:
        VAEConfig(image_size=size)
    except ValueError as exc:
        raise DatasetError(
            f"{where}: {exc} (re-import or regenerate at 32, 64 or 128 px)"
        ) from None
    if data.spec.state is not None:
        states = np.concatenate([data.state1, data.state2]).reshape(2 * len(data), -1)
        if len(np.unique(states, axis=0)) < 2:
            raise DatasetError(f"{where}: every image shows one state; a plan needs two or more")
    moved, still = int((data.a == 1).sum()), int((data.a == 0).sum())
    if moved < MIN_ACTION_PAIRS:
        raise DatasetError(
            f"{where}: {moved} action pairs; a model needs at least {MIN_ACTION_PAIRS} "
            "(the roadmap's edges and the APN are learned from them)"
        )
    if still < MIN_NO_ACTION_PAIRS:
        raise DatasetError(
            f"{where}: {still} no-action pairs; a model needs at least {MIN_NO_ACTION_PAIRS} "
            "(the roadmap's epsilon is measured on them: record a state twice, ideally under two "
            "looks)"
        )


def vae_steps(pairs: int, batch_size: int = TrainConfig.batch_size) -> int:
    """DEFAULT_STEPS, or MIN_EPOCHS passes over a dataset large enough to need more."""
    return max(DEFAULT_STEPS, MIN_EPOCHS * math.ceil(pairs / batch_size))


class Choices:
    """Where each setting comes from, in order: given, the dataset's task.json settings,
    measured for its task (`Task.roadmap_settings`), the default; `why` says which."""

    def __init__(self, task: str, settings: dict[str, Any]) -> None:
        self.task, self.settings = task, settings
        try:
            self.own = get_task(task).roadmap_settings
        except TaskError:  # a task known only from its data: nothing measured for it
            self.own = Task.roadmap_settings
        self.why: list[str] = []

    def pick(self, name: str, given: Any, key: str, default: Any, reason: str) -> Any:
        if given is not None:
            self.why.append(f"{name} {given}: given")
            return given
        if self.settings.get(key) is not None:
            value, source = self.settings[key], "the dataset's task.json settings"
        elif self.own.get(key) is not None:
            value, source = self.own[key], f"measured for {self.task} (docs/tasks)"
        else:
            value, source = default, reason
        self.why.append(f"{name} {value}: {source}")
        return value

    def roadmap(
        self,
        metric: str,
        eps_rule: EpsilonRule | None = None,
        w_eps: float | None = None,
        min_samples: int | None = None,
    ) -> RoadmapConfig:
        """Algorithm 1's settings, as `lsr train model` and `lsr build-roadmap` both choose."""
        rule = self.pick("epsilon rule", eps_rule, "eps_rule", "stable", "the stable cut")
        w = self.pick("w_eps", w_eps, "w_eps", 1.0, "Algorithm 1's fallback")
        least = self.pick(
            "min_samples", min_samples, "min_samples", None, "a tenth of the typical region"
        )
        rare = least is None and self.pick(
            "keep_rare", None, "keep_rare", True, "a small region with moves of its own is a state"
        )
        return RoadmapConfig(
            metric=metric,
            eps_rule=rule,
            w_eps=float(w),
            min_samples=None if least is None else int(least),
            keep_rare=bool(rare),
        )


def choose(
    data: Dataset, recipe: Recipe
) -> tuple[TrainConfig | None, RoadmapConfig, APNTrainConfig, list[str]]:
    """The three steps' settings for this dataset (no VAE's where one is given), and a line
    saying where each came from."""
    settings = data.manifest.get("settings") or {}
    choices = Choices(data.task, settings)
    pick, why = choices.pick, choices.why
    dm = settings.get("d_m")
    vae: TrainConfig | None = None  # nothing to train: its steps and d_m were chosen back then
    if recipe.vae is not None:
        why.append(f"vae {recipe.vae}: given, trained before (metric {recipe.metric})")
    else:
        steps = pick(
            "vae steps",
            recipe.vae_steps,
            "vae_steps",
            vae_steps(len(data)),
            f"{len(data)} tuples: max({DEFAULT_STEPS}, {MIN_EPOCHS} epochs)",
        )
        source = "the paper's for the task" if dm is None else "the dataset's task.json settings"
        why.append(f"d_m {TrainConfig(metric=recipe.metric, dm=dm).d_m(data.task)}: {source}")
        if recipe.augment:
            why.append("augment: the encoder saw each image under a drawn look (--augment)")
        vae = TrainConfig(
            metric=recipe.metric,
            dm=dm,
            steps=int(steps),
            seed=recipe.seed,
            device=recipe.device,
            augment=recipe.augment,
        )
    metric = "l1" if recipe.metric == "none" else recipe.metric
    roadmap = choices.roadmap(metric, recipe.eps_rule, recipe.w_eps, recipe.min_samples)
    apn = APNTrainConfig(
        **({"steps": recipe.apn_steps} if recipe.apn_steps is not None else {}),
        seed=recipe.seed,
        restarts=recipe.apn_restarts,
        device=recipe.device,
    )
    why.append(f"apn restarts {recipe.apn_restarts}: the lowest validation loss kept")
    if data.spec.undo:
        swaps = ", ".join(" <-> ".join(pair) for pair in data.spec.undo)
        why.append(f"apn undo: every pair also taught backwards ({swaps} undoes a move)")
    return vae, roadmap, apn, why


def train_model(
    data_dir: Path | str,
    out: Path | str,
    recipe: Recipe | None = None,
    overwrite: bool = False,
    progress: bool = True,
    say: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Train VAE, roadmap (calibrated) and APN from `data_dir` into `out`; the figures."""
    recipe = recipe or Recipe()
    out = Path(out)
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise ValueError(f"{out}: exists and is not empty; choose another --out or --overwrite")
    data = load_dataset(data_dir)
    check_trainable(data, data_dir)
    reused = reuse_vae(recipe.vae, data) if recipe.vae is not None else None
    if reused is not None:  # the roadmap is built in the metric the VAE was trained with
        recipe = replace(recipe, metric=reused["train"]["metric"])
    vae_cfg, roadmap_cfg, apn_cfg, why = choose(data, recipe)
    counts = {"tuples": len(data), "action_pairs": int(data.a.sum())}
    say(
        f"{data.task}: {counts['tuples']} tuples ({counts['action_pairs']} action pairs), "
        f"{data.image_size} px"
    )
    for line in why:
        say(f"  {line}")
    partial = out.with_name(out.name + ".partial")
    source = Path(recipe.vae).resolve() if recipe.vae else None
    for child in partial.iterdir() if partial.exists() else ():
        if source is None or child.resolve() not in (source, *source.parents):  # not its VAE
            shutil.rmtree(child) if child.is_dir() else child.unlink()
    started = time.perf_counter()
    trained: float | None = None
    try:
        if vae_cfg is not None:  # else reused, checked above
            say(f"[1/3] VAE-{recipe.metric}, {vae_cfg.steps} steps")
            final = train_vae(data_dir, partial / "vae", vae_cfg, progress=progress)
        else:
            say(f"[1/3] VAE-{recipe.metric} trained before: {recipe.vae}")
            if source != (partial / "vae").resolve():
                shutil.copytree(recipe.vae, partial / "vae")
            final = reused["final"]
        check_spread(final, recipe.metric)
        trained = time.perf_counter()
        say("[2/3] roadmap (Algorithm 1) and what it knows")
        built = build_from_dataset(partial / "vae", data_dir, roadmap_cfg, partial / "roadmap")
        say("[3/3] APN")
        threads = torch.get_num_threads()
        torch.set_num_threads(1)  # a 7k-parameter MLP: a second thread only spin-waits
        try:
            apn = train_apn(
                partial / "vae", data_dir, partial / "apn", apn_cfg, progress, partial / "roadmap"
            )
        finally:
            torch.set_num_threads(threads)
        figures = {
            "task": data.task,
            **counts,
            "nodes": built["nodes"],
            "edges": built["edges"],
            "epsilon": built["epsilon"],
            "eps_rule": built["eps_rule"],
            **{k: built[k] for k in ("mean_purity", "pure_nodes") if k in built},
            "known_training_images": built["known_training_images"],
            "vae": {k: final.get(k) for k in ("noaction_max", "action_min", "gap")},
            "apn_val_loss": apn["best"].get("val_loss"),
            "seconds": time.perf_counter() - started,
            "vae_seconds": trained - started,
        }
        record = {"data": str(data_dir), "chosen": why, "figures": figures}
        if reused is not None:
            record["vae"] = str(recipe.vae)
        (partial / RECORD).write_text(json.dumps(record, indent=2) + "\n")
        publish(partial, out)
    except BaseException:
        if trained is None:
            shutil.rmtree(partial, ignore_errors=True)
        else:  # the hour's work is the VAE: kept for the step commands, not thrown away
            say(
                f"{partial / 'vae'}: the trained VAE is kept; go on from it with other settings: "
                f"lsr train model --data {data_dir} --out {out} --vae {partial / 'vae'} ..., "
                "or step by step (lsr build-roadmap, lsr train apn)"
            )
        raise
    return figures
