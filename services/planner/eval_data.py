"""`lsr eval vfm` for a task defined by its data: what a roadmap shows without state labels.

Table I needs the true state of every image; a recorded dataset has none. What it does have:
episodes, which pairs are actions, and the test images themselves. So this reports the
roadmap's size and pruning, how many nodes each training episode passes through, and for the
unseen test images whether the node the planner starts (or ends) a plan at really holds the
image's encoding (it lies within epsilon of one of that node's training members, as Algorithm 1
would have merged it), whether an action pair's images sit on two nodes joined by an edge and a
no-action pair's on one node, and how often random test start/goal pairs get a plan.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from services.encoder.checkpoint import encode_images, load_vae
from services.planner.evaluate import sample_test_pairs
from services.planner.members import MEMBERS, Members, interleave
from services.planner.roadmap import Roadmap
from services.planner.versions import roadmap_dir
from shared.dataset import load_dataset


def _distance(a: np.ndarray, b: np.ndarray, metric: str) -> np.ndarray:
    """Distances of each row of `a` (N, D) to each row of `b` (M, D): (N, M)."""
    diff = np.abs(a[:, None, :] - b[None, :, :])
    if metric == "l1":
        return diff.sum(-1)
    if metric == "l2":
        return np.sqrt((diff**2).sum(-1))
    return diff.max(-1)


def held(
    roadmap: Roadmap, z: np.ndarray, nodes: np.ndarray, members: np.ndarray, point_node: np.ndarray
) -> np.ndarray:
    """Whether each latent of `z` lies within epsilon of a member of `nodes[i]`."""
    out = np.zeros(len(z), dtype=bool)
    for node in np.unique(nodes):
        rows = np.flatnonzero(nodes == node)
        own = members[point_node == node]
        for chunk in np.array_split(rows, max(1, len(rows) // 256)):
            near = _distance(z[chunk], own, roadmap.config.metric).min(1)
            out[chunk] = near < roadmap.epsilon
    return out


def run_data_eval(
    model_dir: Path | str,
    test_dir: Path | str,
    pairs: int = 1000,
    seed: int = 0,
    max_paths: int = 1000,
    train_dir: Path | str | None = None,
) -> dict[str, Any]:
    started = time.perf_counter()
    model_dir = Path(model_dir)
    vae, config = load_vae(model_dir / "vae")
    folder = roadmap_dir(model_dir)
    roadmap = Roadmap.load(folder)
    train = load_dataset(train_dir or config["dataset"]["path"])
    test = load_dataset(test_dir)
    size = config["model"]["image_size"]
    if test.image_size != size:
        raise ValueError(f"test images are {test.image_size} px, the VAE takes {size} px")
    kept = Members.load(folder) if (folder / MEMBERS).is_file() else None  # grown: + experience
    built_on = len(roadmap.point_node) if kept is None else 2 * int((kept.experience == 0).sum())
    if len(train) * 2 != built_on:
        raise ValueError(
            f"{train_dir or config['dataset']['path']}: {2 * len(train)} images, the roadmap "
            f"was built on {built_on}; give the training set with --train"
        )
    if kept is not None:
        members = kept.points
    else:
        members = interleave(*(encode_images(vae, x)[0] for x in (train.image1, train.image2)))
    z1, z2 = encode_images(vae, test.image1)[0], encode_images(vae, test.image2)[0]
    n1, n2 = (np.asarray(roadmap.nearest_node(z), dtype=np.int64) for z in (z1, z2))
    h1 = held(roadmap, z1, n1, members, roadmap.point_node)
    h2 = held(roadmap, z2, n2, members, roadmap.point_node)
    group = roadmap.twin_group  # nodes of one state (twins) count as one
    edges = {(int(a), int(b)) for a, b in roadmap.group_edges}
    g1, g2 = group[n1], group[n2]
    adjacent = np.array([(min(a, b), max(a, b)) in edges for a, b in zip(g1, g2, strict=True)])
    act = test.a == 1

    row: dict[str, Any] = {
        "model": str(model_dir),
        "task": config["dataset"]["task"],
        "roadmap_metric": roadmap.config.metric,
        "w_eps": roadmap.config.w_eps,
        "min_samples": roadmap.config.min_samples,
        "epsilon": roadmap.epsilon,
        "nodes": len(roadmap.nodes),
        "edges": len(roadmap.edges),
        **{
            k: roadmap.stats.get(k)
            for k in (
                "regions_before_pruning",
                "regions_too_small",
                "regions_isolated",
                "points_without_node",
                "edge_weight",
                "action_pairs",
            )
        },
    }
    if train.episode is not None:
        episode_points = np.repeat(train.episode, 2)
        counts = [
            len(set(roadmap.point_node[: len(episode_points)][episode_points == e].tolist()) - {-1})
            for e in np.unique(train.episode)
        ]
        row["nodes_per_episode"] = {
            "episodes": len(counts),
            "mean": float(np.mean(counts)),
            "median": float(np.median(counts)),
            "max": int(np.max(counts)),
        }
    images = np.concatenate([h1, h2])
    row |= {
        "test_images": len(images),
        "test_images_held_by_their_node": 100.0 * float(images.mean()),
        "test_action_pairs": int(act.sum()),
        "action_pairs_on_an_edge": 100.0 * float(adjacent[act].mean()) if act.any() else None,
        "test_no_action_pairs": int((~act).sum()),
        "no_action_pairs_on_one_node": (
            100.0 * float((g1 == g2)[~act].mean()) if (~act).any() else None
        ),
    }
    # Random start/goal pairs of distinct test images, as Table I draws them.
    z_all, n_all, h_all = interleave(z1, z2), interleave(n1, n2), interleave(h1, h2)
    chosen = sample_test_pairs(len(z_all), pairs, seed)
    found = lengths = both_held = 0
    for s, g in chosen:
        paths = roadmap.shortest_paths(int(n_all[s]), int(n_all[g]), max_paths=max_paths)
        if paths:
            found += 1
            lengths += len(paths[0])
            both_held += bool(h_all[s] and h_all[g])
    row |= {
        "pairs": len(chosen),
        "with_a_plan": 100.0 * found / max(1, len(chosen)),
        "plan_ends_hold_start_and_goal": 100.0 * both_held / max(1, len(chosen)),
        "mean_plan_images": lengths / found if found else None,
        "seconds": time.perf_counter() - started,
    }
    return row
