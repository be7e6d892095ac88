"""`lsr explore`: spend an action budget in the simulator where the roadmap is thin, and grow it.

The explorer uses no task rules to choose: it starts from the recorded states where the roadmap
is thin (a state whose best-joined node is in a small component or has few edges, or which no
node holds), and tries actions the APN proposes towards nodes it has no edge to, those
with few edges first (most of them), or actions drawn from the task's action spec. The world
executes what it can and refuses the rest, which is recorded as nothing changed. Every
`grow_every` actions the roadmap grows in memory from what was seen, so that the next choices
follow its new shape; at the end the experience grows the model's roadmap into a new version
(`lsr roadmap grow`). The rules only judge the result afterwards (`lsr eval`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from services.apn.train import propose
from services.data.experience import ExperienceLog, Recorder, tuple_arrays
from services.encoder.checkpoint import read_vae_config
from services.planner.action_plans import ActionPlanner
from services.planner.grow import grow, grow_model, load_members, state_labels
from services.planner.members import Members
from services.planner.roadmap import Roadmap, pair_distances
from services.sim.workcell import Observer
from services.sim.worlds import make_world
from shared.appearance import trained_appearance
from shared.tasks import has_simulator
from shared.tasks.base import IllegalActionError, Task, WorldError
from shared.tasks.spec import ArraySpec

NEAR = 8  # targets drawn among this many nearest candidate nodes


@dataclass(frozen=True)
class ExploreConfig:
    actions: int  # the budget: actions tried in the world, refused ones included
    seed: int = 0
    grow_every: int = 100  # actions between in-memory growths
    # Where actions come from: the APN towards a nearby node it has no edge to, an action
    # the roadmap's pairs show (from somewhere else), or a draw from the spec; the rest APN.
    seen_share: float = 0.1
    spec_share: float = 0.05
    chain: int = 3  # actions in a row from one start before choosing another
    # Looks again (the scene perturbed slightly, as a camera sees it again) after each executed
    # action, recorded as no-action pairs: a state reached for the first time then has enough
    # images to found a node (growth's NEW_NODE_MIN) in one visit.
    looks: int = 0

    def __post_init__(self) -> None:
        if self.actions < 1 or self.grow_every < 1 or self.chain < 1 or self.looks < 0:
            raise ValueError("actions, grow_every and chain must be at least 1, looks >= 0")
        shares = (self.seen_share, self.spec_share)
        if min(shares) < 0 or sum(shares) > 1:
            raise ValueError(
                f"seen_share and spec_share must be >= 0 and sum to <= 1, got {shares}"
            )


def shape_of(roadmap: Roadmap) -> tuple[np.ndarray, np.ndarray]:
    """(component of each node, twins joined; degree of each node)."""
    return roadmap.component, np.bincount(roadmap.edges.ravel(), minlength=roadmap.num_nodes)


def thinness(graph: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """How much each node asks to be explored from: small components and few edges first (1
    for a node alone). `graph`: each node's component and degree, as shape_of gives them."""
    component, degree = graph
    size = np.bincount(component)[component]
    return 1.0 / ((1.0 + degree) * size)


def starts(
    task: Task, roadmap: Roadmap, graph: tuple[np.ndarray, np.ndarray], members: Members
) -> tuple[list[Any], np.ndarray]:
    """Where the explorer may start (each recorded state once) and how much each asks to be
    explored from: as little as its best-joined node (thinness), 1 for a state no node holds.
    A state seen only standing still (a no-action pair, no move) is pruned from the roadmap:
    box stacking at 300 tuples + 2000 actions, every state recorded, left 11 states without a
    move when only nodes were starts. A state's looks may split it into nodes, one joined and
    twins alone: weighed by node, those twins drew most starts (141 of 254 nodes outside the
    largest component showed a state it held) and two states stayed joined only to each other
    at three explore seeds of four."""
    labels = state_labels(roadmap, members, task)
    held = labels.members > 0  # nodes with a recorded state (a robot's images come without)
    loose = np.flatnonzero((roadmap.point_node < 0) & members.has_state.astype(bool))
    arrays = np.concatenate([labels.states[held], members.states[loose]])
    own = np.concatenate([thinness(graph)[held], np.ones(len(loose))])
    flat = arrays.reshape(len(arrays), -1)
    distinct, which = np.unique(flat, axis=0, return_inverse=True)
    weight = np.full(len(distinct), np.inf)
    np.minimum.at(weight, which.ravel(), own)
    shape = members.states.shape[1:]
    return [task.array_to_state(s.reshape(shape)) for s in distinct], weight


def spec_action(spec: ArraySpec, rng: np.random.Generator) -> np.ndarray:
    """An action drawn uniformly from what the spec allows."""
    low = spec.start
    values = [rng.integers(low, low + c) for c in spec.counts]
    return np.asarray(values, dtype=spec.dtype).reshape(spec.shape)


def _target(
    roadmap: Roadmap,
    graph: tuple[np.ndarray, np.ndarray],
    z: np.ndarray,
    node: int,
    step: float,
    rng: np.random.Generator,
) -> int:
    """A node to head for: one of the NEAR nodes whose latent distance from `z` is closest to
    one action's (`step`), those with fewer edges more often, among those in other components
    where there are any, else among those without an edge from here. An action-shaped latent
    space puts the states one action apart about that far apart, so the APN's action towards
    such a node is often one that can be done (box stacking at 500 tuples: 39% of proposals
    legal, against 7% towards the nearest nodes). `graph`: each node's component and degree, as
    shape_of gives them."""
    component, degree = graph
    others = np.flatnonzero(component != component[node])
    if not len(others):  # not this node, its twins or its neighbours' groups
        group = roadmap.twin_group
        others = np.flatnonzero(~np.isin(group, [group[node], *roadmap.neighbours(node)]))
    if not len(others):
        return node
    gaps = pair_distances(roadmap.nodes[others], z, roadmap.config.metric)
    near = others[np.argsort(np.abs(gaps - step))[:NEAR]]
    # Thin ones first: a node with few edges is a state seen but hardly moved from or to
    # (box stacking at 300 tuples + 2000 actions, two seeds: 283 states joined by moves, 280
    # drawn alike; the rest are states no image showed, which no target names).
    weight = 1.0 / (1.0 + degree[near]) ** 2
    return int(rng.choice(near, p=weight / weight.sum()))


def action_step(members: Members, metric: str) -> float:
    """How far apart one action takes the latents: the median over the action pairs."""
    moved = np.flatnonzero(members.a == 1)
    if not len(moved):
        return 0.0
    return float(
        np.median(pair_distances(members.points[2 * moved], members.points[2 * moved + 1], metric))
    )


def explore(
    model_dir: Path | str,
    cfg: ExploreConfig,
    experience: Path | str,
    data_dir: Path | str | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Explore, record into `experience`, then grow the model's roadmap from it."""
    started = time.perf_counter()
    model_dir = Path(model_dir)
    planner = ActionPlanner.from_model_dir(model_dir)
    task: Task = planner.task
    if not has_simulator(task.name):
        raise ValueError(f"task {task.name!r} has no simulator: lsr explore needs one")
    vae = planner.planner.vae
    roadmap = base = planner.planner.roadmap
    calibration = planner.planner.calibration
    members = load_members(model_dir, vae, data_dir)
    graph = shape_of(roadmap)  # (component, degree) of each node
    places, weight = starts(task, roadmap, graph, members)
    config = read_vae_config(model_dir / "vae")
    size = int(config["model"]["image_size"])
    log = ExperienceLog(experience, task.spec, size, source="explore")
    record = Recorder(log, task)
    rng = np.random.default_rng(cfg.seed)
    new: Members | None = None  # what was seen, encoded at the last growth
    rows: list[tuple] = []  # what was seen since
    tried = refused = grown_at = 0
    sources = {"apn": 0, "seen": 0, "spec": 0}
    seen = members.actions[members.a == 1]
    step = action_step(members, roadmap.config.metric)
    shape = {"nodes": roadmap.num_nodes, "edges": len(roadmap.edges)}
    shape["components"] = int(graph[0].max() + 1)
    bar = tqdm(total=cfg.actions, desc="explore", unit="action", disable=not progress)
    bar.set_postfix(shape)
    appearance = trained_appearance(config)
    with make_world(task.name, size, appearance=appearance) as world:
        observer = Observer(world)  # images as the model is given them: registered
        while tried < cfg.actions:
            if not weight.sum():
                raise ValueError(f"{model_dir}: nothing recorded has a state to start at")
            state = world.reset(places[rng.choice(len(places), p=weight / weight.sum())], rng)
            for _ in range(cfg.chain):
                if tried >= cfg.actions:
                    break
                image, why = observer.look()
                if why is not None:  # its markers were not found: start elsewhere
                    break
                z = planner.encode(image)
                here = int(roadmap.nearest_node(z))
                draw = rng.random()
                if draw < cfg.spec_share:
                    source, array = "spec", spec_action(task.spec.action, rng)
                elif draw < cfg.spec_share + cfg.seen_share:
                    source = "seen" if len(seen) else "spec"
                    array = (
                        seen[rng.integers(len(seen))]
                        if len(seen)
                        else spec_action(task.spec.action, rng)
                    )
                else:
                    there = _target(roadmap, graph, z, here, step, rng)
                    arrays, _ = propose(planner.apn, z[None], roadmap.nodes[there][None])
                    source, array = "apn", arrays[0]
                sources[source] += 1
                tried += 1
                bar.update(1)
                action = task.array_to_action(array)
                try:
                    if action is None:
                        raise IllegalActionError("no action")
                    after_state = world.execute(action, rng)
                except IllegalActionError:
                    refused += 1
                    action, after_state = None, state
                except WorldError:  # a wrecked scene: start elsewhere
                    break
                after, why = observer.look()
                if why is not None:
                    break
                if action is not None or not np.array_equal(after, image):
                    # (an identical look after a refusal shows nothing new: not recorded)
                    rows.append((image, action, after, state, after_state))
                    record(*rows[-1])
                for _ in range(cfg.looks if action is not None else 0):
                    after_state = world.perturb(rng)
                    again, why = observer.look()
                    if why is not None:
                        break
                    rows.append((after, None, again, after_state, after_state))
                    record(*rows[-1])
                    after = again
                state = after_state
                if tried >= grown_at + cfg.grow_every and rows:
                    grown_at = tried
                    fresh = _encode(vae, task, rows)
                    new, rows = fresh if new is None else new + fresh, []
                    roadmap, _, everything, _ = grow(base, calibration, members, new, task)
                    graph = shape_of(roadmap)
                    places, weight = starts(task, roadmap, graph, everything)
                    shape = {"nodes": roadmap.num_nodes, "edges": len(roadmap.edges)}
                    shape["components"] = int(graph[0].max() + 1)
                    bar.set_postfix(shape)
    bar.close()
    record.flush()
    explored = time.perf_counter() - started
    # Nothing recorded (every action refused, in a world that draws alike): nothing to grow.
    report = grow_model(model_dir, [experience], data_dir) if record.recorded else None
    return {
        "actions": tried,
        "refused": refused,
        "sources": sources,
        "recorded": record.recorded,
        "explore_seconds": explored,
        "growth": report,
    }


def _encode(vae: Any, task: Task, rows: list[tuple]) -> Members:
    image1, image2, u, state1, state2 = tuple_arrays(task, rows)
    return Members.of_images(vae, image1, image2, u, (u >= 0).any(axis=1), (state1, state2))
