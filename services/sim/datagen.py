"""Dataset generation: action and no-action pairs rendered by the simulated world.

Every tuple draws its randomness from its own seed (dataset seed, tuple index, attempt), so the
bytes written do not depend on the number of worker processes.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from tqdm import tqdm

from shared import dataset as ds
from shared.appearance import CLEAN, get_appearance, task_default
from shared.tasks import get_task
from shared.tasks.base import Task, World, WorldError

# A walk is started again this often before the run stops: T-shirt moves fail about 1 in 100.
MAX_ATTEMPTS = 5


@dataclass(frozen=True)
class GenerateConfig:
    task: str = "box_stacking"
    pairs: int = 5000
    seed: int = 0
    image_size: int = 64
    action_fraction: float = 0.65
    shard_size: int = 1000
    workers: int = min(2, os.cpu_count() or 1)
    episode_length: int | None = None  # tuples walked from one reset; None: the world's default
    # "balanced": episodes start from every state in turn (a fresh seeded order each round, the
    # action and no-action episodes each going round), so 1000 box-stacking tuples show every
    # one of the 288 states in an action pair; "random": each start drawn independently, as
    # before this option existed (with 1000 tuples, 1-2 states never appeared).
    starts: Literal["balanced", "random"] = "balanced"
    world_options: dict[str, Any] = field(default_factory=dict)  # e.g. {"lattice": 5}
    # How the images look (shared.appearance): "clean" renders as before this option existed;
    # "camera" varies lights, camera pose, table and the camera's pipeline, drawn per episode
    # from the episode's own seed; "shifted" doubles every range (test data only). None: the
    # task's default (`shared.appearance.task_default`: camera for the T-shirt, else clean).
    appearance: str | None = None

    def __post_init__(self) -> None:
        if self.pairs < 1:
            raise ValueError(f"pairs must be at least 1, got {self.pairs}")
        if not 0.0 <= self.action_fraction <= 1.0:
            raise ValueError(f"action_fraction must be in [0, 1], got {self.action_fraction}")
        if self.shard_size < 1 or self.workers < 1:
            raise ValueError("shard_size and workers must be at least 1")
        if self.episode_length is not None and self.episode_length < 1:
            raise ValueError(f"episode_length must be at least 1, got {self.episode_length}")
        if self.starts not in ("balanced", "random"):
            raise ValueError(f"starts must be balanced or random, got {self.starts!r}")
        if self.appearance is None:
            object.__setattr__(self, "appearance", task_default(self.task))
        get_appearance(self.appearance)  # names the field and the known levels
        if self.image_size not in range(16, 1025):
            raise ValueError(f"image_size {self.image_size} is out of range 16..1024")


def action_flags(cfg: GenerateConfig) -> np.ndarray:
    """Which tuples are action pairs: an exact share, in a seeded random order."""
    flags = np.zeros(cfg.pairs, dtype=np.uint8)
    flags[: round(cfg.action_fraction * cfg.pairs)] = 1
    np.random.default_rng(cfg.seed).shuffle(flags)
    return flags


def balanced_starts(task: Task, seed: int, first_flags: list[int]) -> list[int | None]:
    """Index into task.all_states() of each episode's first state, by the episode's first flag:
    the action episodes go round all states in seeded orders, and so do the no-action ones.
    None for every episode when the task cannot enumerate its states (then they are drawn)."""
    states = task.all_states()
    if states is None:
        return [None] * len(first_flags)
    rng = np.random.default_rng([seed, 1])  # a stream of its own: tuples keep theirs
    orders: dict[int, list[int]] = {0: [], 1: []}
    out: list[int | None] = []
    for flag in first_flags:
        if not orders[flag]:
            orders[flag] = rng.permutation(len(states)).tolist()[::-1]
        out.append(orders[flag].pop())
    return out


def make_episode(
    task: Task, world: World, seed: int, start: int, flags: list[int], first: int | None = None
) -> tuple[list[dict], int]:
    """Tuples start .. start + len(flags) - 1: one walk from state `first` (an index into
    task.all_states(), or None for a random state), each tuple's second state the next one's
    first. Seeded by (seed, start, attempt) alone, so the bytes do not depend on how episodes
    are spread over workers (a camera-like world seeds its look from the same rng's state at
    reset, without drawing from it); a walk whose physics fails starts again. Returns the tuples and
    the number of failed attempts before them."""
    for attempt in range(MAX_ATTEMPTS):
        rng = np.random.default_rng([seed, start, attempt])
        try:
            sampled = task.sample_state(rng)  # drawn either way: the rng stream stays the same
            state1 = sampled if first is None else task.all_states()[first]
            if world.reset(state1, rng) != state1:
                raise WorldError("settled state differs from the placed one")
            rows = []
            for is_action in flags:
                image1 = world.render()
                action = None
                if is_action:
                    legal = task.legal_actions(state1)
                    action = world.demonstrated(legal[int(rng.integers(len(legal)))], rng)
                    state2 = world.execute(action, rng)
                    if state2 != task.apply(state1, action):
                        raise WorldError(f"executing {action} gave an unexpected state {state2}")
                else:
                    state2 = world.perturb(rng)
                    if state2 != state1:
                        raise WorldError("the perturbed state differs from the placed one")
                rows.append(
                    {
                        "image1": image1,
                        "image2": world.render(),
                        "a": np.uint8(is_action),
                        "u": task.action_to_array(action),
                        "state1": task.state_to_array(state1),
                        "state2": task.state_to_array(state2),
                    }
                )
                state1 = state2
            return rows, attempt
        except WorldError as exc:
            last = exc
    raise WorldError(f"episode at tuple {start}: physics failed {MAX_ATTEMPTS} times, last: {last}")


_worker: tuple[Task, World] | None = None


def _init_worker(
    task_name: str, image_size: int, options: dict[str, Any], appearance: str = CLEAN
) -> None:
    global _worker
    from services.sim.worlds import make_world

    world = make_world(task_name, image_size, appearance=appearance, **options)
    _worker = (get_task(task_name), world)


Episode = tuple[int, list[int], int | None]  # first tuple, action flags, first state's index


def _make_chunk(job: tuple[int, list[Episode]]) -> tuple[list[dict], int]:
    assert _worker is not None
    seed, episodes = job
    task, world = _worker
    rows, retries = [], 0
    for start, flags, first in episodes:
        made, failed = make_episode(task, world, seed, start, flags, first)
        rows += made
        retries += failed
    return rows, retries


def _stack(rows: list[dict]) -> dict[str, np.ndarray]:
    return {f: np.stack([r[f] for r in rows]) for f in ds.FIELDS}


def generate(
    cfg: GenerateConfig, out: Path | str, overwrite: bool = False, progress: bool = True
) -> dict[str, Any]:
    """Write a dataset folder; built beside `out` and moved in place only when complete."""
    out = Path(out)
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise FileExistsError(f"{out} exists and is not empty; pass overwrite to replace it")
    spec = get_task(cfg.task).spec  # fails fast on an unknown task
    from services.sim.worlds import world_class

    partial = out.with_name(f".{out.name}.partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)

    flags = action_flags(cfg)
    length = cfg.episode_length or world_class(cfg.task).episode_length
    begins = range(0, cfg.pairs, length)
    firsts: list[int | None] = (
        balanced_starts(get_task(cfg.task), cfg.seed, [int(flags[s]) for s in begins])
        if cfg.starts == "balanced"
        else [None] * len(begins)
    )
    episodes: list[Episode] = [
        (s, flags[s : s + length].tolist(), first) for s, first in zip(begins, firsts, strict=True)
    ]
    per_job = max(1, 25 // length)  # about 25 tuples a job
    jobs = [(cfg.seed, episodes[i : i + per_job]) for i in range(0, len(episodes), per_job)]
    started = time.perf_counter()
    shards: list[dict[str, Any]] = []
    pending: list[dict] = []
    retries = 0  # episodes started again after the physics failed

    def flush(rows: list[dict]) -> None:
        name = ds.shard_name(len(shards))
        sha = ds.write_shard(partial / name, _stack(rows), spec)
        shards.append({"file": name, "count": len(rows), "sha256": sha})

    bar = tqdm(total=cfg.pairs, unit="pair", desc=f"generate {cfg.task}", disable=not progress)
    if cfg.workers == 1:
        _init_worker(cfg.task, cfg.image_size, cfg.world_options, cfg.appearance)
        results = map(_make_chunk, jobs)
        pool = None
    else:
        init = (cfg.task, cfg.image_size, cfg.world_options, cfg.appearance)
        pool = mp.get_context("spawn").Pool(cfg.workers, initializer=_init_worker, initargs=init)
        results = pool.imap(_make_chunk, jobs)
    try:
        for rows, failed in results:
            retries += failed
            pending.extend(rows)
            bar.update(len(rows))
            while len(pending) >= cfg.shard_size:
                flush(pending[: cfg.shard_size])
                pending = pending[cfg.shard_size :]
        if pending:
            flush(pending)
    finally:
        bar.close()
        if pool is not None:
            pool.terminate()
    seconds = time.perf_counter() - started

    n_action = int(flags.sum())
    manifest = {
        "format": ds.FORMAT,
        "version": ds.VERSION,
        "task": cfg.task,
        "spec": spec.to_json(),
        "image_size": cfg.image_size,
        "appearance": get_appearance(cfg.appearance).to_json(),  # how the images look
        "seed": cfg.seed,
        "counts": {
            "tuples": cfg.pairs,
            "action_pairs": n_action,
            "no_action_pairs": cfg.pairs - n_action,
        },
        "config": {
            **{k: v for k, v in asdict(cfg).items() if k != "workers"},
            "episode_length": length,
        },
        "shards": shards,
        "physics_retries": retries,
    }
    ds.write_manifest(partial, manifest)
    ds.publish(partial, out)
    return {**manifest, "seconds": seconds, "images_per_second": 2 * cfg.pairs / seconds}
