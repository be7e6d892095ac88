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
from typing import Any, Literal, NamedTuple

import numpy as np
from tqdm import tqdm

from shared import dataset as ds
from shared.appearance import CLEAN, get_appearance, task_default
from shared.registration import RegistrationError
from shared.tasks import DEFAULT_TASK, get_task
from shared.tasks.base import Task, World, WorldError

# A walk is started again this often before the run stops: T-shirt moves fail about 1 in 100.
MAX_ATTEMPTS = 5
# A frame whose markers are not found is looked at again under a fresh look this often.
MAX_LOOKS = 5


# No-action pairs across two looks where looks vary: every shipped camera model was trained
# with this share, and on 2000 cloth tuples it measured better than none at `shifted` and
# `clean` (docs/camera.md, "Look pairs measure better"); not yet measured at small data.
LOOK_PAIRS = 0.5


@dataclass(frozen=True)
class GenerateConfig:
    task: str = DEFAULT_TASK
    pairs: int = 5000
    seed: int = 0
    image_size: int = 64
    action_fraction: float = 0.65
    shard_size: int = 1000
    workers: int = min(2, os.cpu_count() or 1)
    episode_length: int | None = None  # tuples walked from one reset; None: `episode_length()`
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
    # The share of no-action pairs whose second image is the same state under a fresh draw of
    # the look (lights, table, camera), as a robot sees it again after the light or the camera
    # changed; 0: both images share their episode's look, as before this option existed. None:
    # LOOK_PAIRS where looks vary (every shipped camera model was trained so), 0 at clean.
    look_pairs: float | None = None

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
        if self.look_pairs is None:
            look_pairs = 0.0 if self.appearance == CLEAN else LOOK_PAIRS
            object.__setattr__(self, "look_pairs", look_pairs)
        if not 0.0 <= self.look_pairs <= 1.0:
            raise ValueError(f"look_pairs must be in [0, 1], got {self.look_pairs}")
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
    the action episodes go round all states in seeded orders, and so do the no-action ones,
    each of their rounds taking first the states started from least so far, the action
    episodes' starts counted: a recording with as many episodes as states starts once from
    every state (300 box-stacking tuples showed 252 of the 288 states when the two went round
    apart, and an explorer starts only from states a recording showed).
    None for every episode when the task cannot enumerate its states (then they are drawn)."""
    states = task.all_states()
    if states is None:
        return [None] * len(first_flags)
    rng = np.random.default_rng([seed, 1])  # a stream of its own: tuples keep theirs
    count = np.zeros(len(states), dtype=np.int64)
    moves = _rounds(rng, count, sum(1 for flag in first_flags if flag))
    stills = _rounds(rng, count, len(first_flags) - len(moves))
    orders = {1: moves[::-1], 0: stills[::-1]}
    return [orders[1 if flag else 0].pop() for flag in first_flags]


def _rounds(rng: np.random.Generator, count: np.ndarray, episodes: int) -> list[int]:
    """`episodes` starts going round the states in seeded orders, the states started from
    least so far (`count`, updated) first in each round."""
    out: list[int] = []
    while len(out) < episodes:
        order = rng.permutation(len(count))
        take = order[np.argsort(count[order], kind="stable")][: episodes - len(out)]
        count[take] += 1
        out.extend(take.tolist())
    return out


class Camera:
    """What a dataset stores of what the world shows (services.sim.workcell.Observer: the
    canonical render at `clean`, else the cell's frame registered to the table frame), a frame
    whose markers are not found looked at again under a fresh look. Keeps what registration
    measured, for the manifest."""

    def __init__(self, world: World) -> None:
        from services.sim.workcell import Observer

        self.world = world
        observer = Observer(world)
        self.registration = observer.registration if observer.frames else None
        self.errors: list[float] = []  # corner RMS, canonical px, per registered frame
        self.offsets: list[float] = []
        self.refused: list[str] = []

    def image(self) -> np.ndarray:
        if self.registration is None:
            return self.world.render()
        for _ in range(MAX_LOOKS):
            try:
                registered = self.registration.register(self.world.frame())  # as observe()
            except RegistrationError as exc:
                self.refused.append(str(exc))
                self.world.relook()  # type: ignore[attr-defined]
                continue
            self.errors.append(registered.error_px)
            self.offsets.append(registered.offset_px)
            return registered.image
        raise WorldError(f"no frame registered in {MAX_LOOKS} looks, last: {self.refused[-1]}")

    def relook(self) -> None:
        self.world.relook()  # type: ignore[attr-defined]


def make_episode(
    task: Task,
    world: World,
    seed: int,
    start: int,
    flags: list[int],
    first: int | None = None,
    camera: Camera | None = None,
    look_pairs: float = 0.0,
) -> tuple[list[dict], int]:
    """Tuples start .. start + len(flags) - 1: one walk from state `first` (an index into
    task.all_states(), or None for a random state), each tuple's second state the next one's
    first. Seeded by (seed, start, attempt) alone, so the bytes do not depend on how episodes
    are spread over workers (a camera-like world seeds its look from the same rng's state at
    reset, without drawing from it); a walk whose physics fails starts again. Returns the tuples and
    the number of failed attempts before them. `look_pairs` > 0 draws from the rng (whether
    each no-action pair spans two looks), so the tuples differ from a run without."""
    camera = camera or Camera(world)
    for attempt in range(MAX_ATTEMPTS):
        rng = np.random.default_rng([seed, start, attempt])
        try:
            sampled = task.sample_state(rng)  # drawn either way: the rng stream stays the same
            state1 = sampled if first is None else task.all_states()[first]
            if world.reset(state1, rng) != state1:
                raise WorldError("settled state differs from the placed one")
            rows = []
            for is_action in flags:
                image1 = camera.image()
                action, spans = None, False
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
                    spans = look_pairs > 0 and bool(rng.random() < look_pairs)
                    if spans:
                        camera.relook()
                rows.append(
                    {
                        "image1": image1,
                        "image2": camera.image(),
                        "a": np.uint8(is_action),
                        "u": task.action_to_array(action),
                        "state1": task.state_to_array(state1),
                        "state2": task.state_to_array(state2),
                        "look_pair": spans,  # not stored: counted for the manifest
                    }
                )
                state1 = state2
            return rows, attempt
        except WorldError as exc:
            last = exc
    raise WorldError(f"episode at tuple {start}: physics failed {MAX_ATTEMPTS} times, last: {last}")


_worker: tuple[Task, Camera, float] | None = None


def _init_worker(
    task_name: str,
    image_size: int,
    options: dict[str, Any],
    appearance: str = CLEAN,
    look_pairs: float = 0.0,
) -> None:
    global _worker
    from services.sim.worlds import make_world

    task = get_task(task_name)
    world = make_world(task_name, image_size, appearance=appearance, **options)
    _worker = (task, Camera(world), look_pairs)


def episode_length(task: Task, pairs: int) -> int:
    """Tuples walked from one reset: the world's longest, shortened so that the episodes go
    round every state at least twice. In episodes of 10, one 300-tuple T-shirt recording in six
    never showed one of its 25 views, and a model from it refused that view; in episodes of 4,
    none did (docs/findings/2026-12-07-a-view-never-recorded.md)."""
    from services.sim.worlds import world_class

    longest = world_class(task.name).episode_length
    states = task.all_states()
    if longest <= 1 or not states:
        return longest
    return max(1, min(longest, pairs // (2 * len(states))))


Episode = tuple[int, list[int], int | None]  # first tuple, action flags, first state's index


class Chunk(NamedTuple):
    rows: list[dict]
    retries: int  # walks started again after the physics failed
    errors: list[float]  # registration's corner RMS per registered frame
    offsets: list[float]
    refused: list[str]  # frames looked at again, and why


def plan_episodes(task: Task, cfg: GenerateConfig, length: int) -> list[Episode]:
    """The recording's episodes of `length` tuples: where each begins, its action flags and its
    first state (balanced starts, or None: drawn)."""
    flags = action_flags(cfg)
    begins = range(0, cfg.pairs, length)
    firsts: list[int | None] = (
        balanced_starts(task, cfg.seed, [int(flags[s]) for s in begins])
        if cfg.starts == "balanced"
        else [None] * len(begins)
    )
    return [
        (s, flags[s : s + length].tolist(), first) for s, first in zip(begins, firsts, strict=True)
    ]


def _make_chunk(job: tuple[int, list[Episode]]) -> Chunk:
    assert _worker is not None
    seed, episodes = job
    task, camera, look_pairs = _worker
    camera.errors, camera.offsets, camera.refused = [], [], []
    rows, retries = [], 0
    for start, flags, first in episodes:
        made, failed = make_episode(
            task, camera.world, seed, start, flags, first, camera, look_pairs
        )
        rows += made
        retries += failed
    return Chunk(rows, retries, camera.errors, camera.offsets, camera.refused)


def _stack(rows: list[dict]) -> dict[str, np.ndarray]:
    return {f: np.stack([r[f] for r in rows]) for f in ds.FIELDS}


def generate(
    cfg: GenerateConfig, out: Path | str, overwrite: bool = False, progress: bool = True
) -> dict[str, Any]:
    """Write a dataset folder; built beside `out` and moved in place only when complete."""
    out = Path(out)
    if out.exists() and any(out.iterdir()) and not overwrite:
        raise FileExistsError(f"{out} exists and is not empty; pass overwrite to replace it")
    task = get_task(cfg.task)  # fails fast on an unknown task
    spec = task.spec

    partial = out.with_name(f".{out.name}.partial")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)

    length = cfg.episode_length or episode_length(task, cfg.pairs)
    episodes = plan_episodes(task, cfg, length)
    per_job = max(1, 25 // length)  # about 25 tuples a job
    jobs = [(cfg.seed, episodes[i : i + per_job]) for i in range(0, len(episodes), per_job)]
    started = time.perf_counter()
    shards: list[dict[str, Any]] = []
    pending: list[dict] = []
    retries = 0  # episodes started again after the physics failed
    errors: list[float] = []
    offsets: list[float] = []
    refused: list[str] = []
    look_pairs = 0

    def flush(rows: list[dict]) -> None:
        name = ds.shard_name(len(shards))
        sha = ds.write_shard(partial / name, _stack(rows), spec)
        shards.append({"file": name, "count": len(rows), "sha256": sha})

    bar = tqdm(total=cfg.pairs, unit="pair", desc=f"generate {cfg.task}", disable=not progress)
    init = (cfg.task, cfg.image_size, cfg.world_options, cfg.appearance, cfg.look_pairs)
    if cfg.workers == 1:
        _init_worker(*init)
        results = map(_make_chunk, jobs)
        pool = None
    else:
        pool = mp.get_context("spawn").Pool(cfg.workers, initializer=_init_worker, initargs=init)
        results = pool.imap(_make_chunk, jobs)
    try:
        for chunk in results:
            retries += chunk.retries
            errors += chunk.errors
            offsets += chunk.offsets
            refused += chunk.refused
            look_pairs += sum(row["look_pair"] for row in chunk.rows)
            pending.extend(chunk.rows)
            bar.update(len(chunk.rows))
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

    n_action = sum(sum(flags) for _, flags, _ in episodes)
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
            "look_pairs": look_pairs,  # no-action pairs whose images span two looks
        },
        # the table's markers (null: none) and how the images were brought to the table frame
        "markers": None if task.workcell is None else task.workcell.to_json(),
        "registration": registration_summary(errors, offsets, refused),
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


def registration_summary(
    errors: list[float], offsets: list[float], refused: list[str]
) -> dict[str, Any] | None:
    """What registration measured over a dataset's frames; None when the images are the
    canonical camera's own renders (nothing registered)."""
    if not errors and not refused:
        return None
    return {
        "frames": len(errors),
        "refused": len(refused),  # frames whose markers were not found: looked at again
        "refusals": sorted(set(refused))[:5],
        "error_px_p50": round(float(np.median(errors)), 3) if errors else None,
        "error_px_max": round(float(np.max(errors)), 3) if errors else None,
        "offset_px_max": round(float(np.max(offsets)), 2) if offsets else None,
    }
