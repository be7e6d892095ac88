"""Experience grows small roadmaps without retraining (issue 22): the figures and the figure.

  explore  A copy of the model; Table I on unseen test pairs; then `lsr explore` in steps of
           --step actions up to --budget, Table I and the roadmap's components after each;
           with --closed-loop N, N closed-loop tasks in simulation at the end.
  loop     A copy of the model; rounds of --loop-pairs ordinary closed-loop tasks in
           simulation recording what they did, the roadmap grown after each round, until
           --budget actions are spent; with --shortcuts P a share P of the steps tries the
           APN's action straight to a node further along the plans (TryShortcuts); Table I
           (detour ratio) after every round.
  timing   --new recorded tuples (from --experience) grown into the model's roadmap, timed.

Each mode prints one JSON line and writes OUT/results.json; explore plots All and the
component count against the actions spent (--figure). The source model is never changed.

  python benchmarks/bench_experience.py explore --model runs/box500 \
      --test data/box_stacking/test --budget 2000 --step 250 --out runs/experience/box500b \
      --figure docs/images/experience_box_stacking.png --label "box stacking, 500 tuples"
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from services.planner.eval_vfm import run_vfm_eval
from services.planner.grow import grow_model
from services.planner.roadmap import Roadmap
from services.planner.versions import roadmap_dir
from services.sim.explore import ExploreConfig, explore, shape_of

TABLE = ("all", "any", "trans", "detour_ratio")


def table1(model: Path, test: Path, pairs: int) -> dict[str, Any]:
    row, _ = run_vfm_eval(model, test, pairs=pairs, seed=0)
    roadmap = Roadmap.load(roadmap_dir(model))
    return {
        **{k: row.get(k) for k in TABLE},
        "nodes": roadmap.num_nodes,
        "edges": len(roadmap.edges),
        "twins": len(roadmap.twins),
        "components": int(shape_of(roadmap)[0].max() + 1),
        **against_states(model, roadmap),
    }


def against_states(model: Path, roadmap: Roadmap) -> dict[str, int]:
    """The roadmap judged by the true states its members carry (the sim records them): images
    in a node of another state (its majority's), edges between states no move links, twins of
    two states. All zero for a roadmap that grew honestly."""
    from services.planner.evaluate import TransitionChecker
    from services.planner.grow import state_labels
    from services.planner.members import MEMBERS, Members
    from shared.tasks import get_task

    folder = roadmap_dir(model)
    if not (folder / MEMBERS).is_file():
        return {}
    task = get_task(json.loads((model / "vae" / "config.json").read_text())["dataset"]["task"])
    labels = state_labels(roadmap, Members.load(folder), task)
    state = {
        n: task.array_to_state(labels.states[n]) for n in np.flatnonzero(labels.members).tolist()
    }
    legal = TransitionChecker(task).legal
    return {
        "images_of_another_state": round(float(labels.members @ (1 - labels.purity))),
        "edges_no_move_links": sum(
            a in state and b in state and not legal(state[a], state[b])
            for a, b in roadmap.edges.tolist()
        ),
        "twins_of_two_states": sum(
            a in state and b in state and state[a] != state[b] for a, b in roadmap.twins.tolist()
        ),
    }


def closed_loop(
    model: Path,
    pairs: int,
    experience: Path | None = None,
    seed: int = 1,
    shortcuts: float = 0.0,
    max_actions: int | None = None,
    tried: set[tuple[int, int]] | None = None,
) -> dict[str, Any]:
    from services.data.experience import ExperienceLog, Recorder
    from services.planner.action_plans import ActionPlanner
    from services.sim.closed_loop import TryShortcuts, evaluate_system
    from services.sim.worlds import make_world

    planner = ActionPlanner.from_model_dir(model)
    task = planner.task
    record = None
    if experience is not None:
        record = Recorder(ExperienceLog(experience, task.spec, planner.image_size), task)
    trying = TryShortcuts(planner, shortcuts, seed, tried)
    already = len(trying.tried)
    with make_world(task.name, planner.image_size) as world:
        result = evaluate_system(
            trying, world, task, pairs, seed=seed, record=record, max_actions=max_actions
        )
    kept = (
        "pairs",
        "success",
        "actions_executed",
        "illegal_actions",
        "steps_over_optimal",
        "outcomes",
    )
    return {k: result[k] for k in kept} | {"shortcuts_tried": len(trying.tried) - already}


def copy_model(source: Path, out: Path) -> Path:
    model = out / "model"
    if model.exists():
        shutil.rmtree(model)
    shutil.copytree(source, model, ignore=shutil.ignore_patterns("experience"))
    return model


def run_explore(args: argparse.Namespace) -> dict[str, Any]:
    model = copy_model(args.model, args.out)
    experience = args.out / "experience"
    shutil.rmtree(experience, ignore_errors=True)
    rows = [{"actions": 0, **table1(model, args.test, args.pairs)}]
    print(json.dumps(rows[-1]), flush=True)
    spent, seed = 0, args.seed
    while spent < args.budget and rows[-1]["all"] < args.stop_at:
        step = min(args.step, args.budget - spent)
        cfg = ExploreConfig(actions=step, seed=seed, looks=args.looks)
        report = explore(model, cfg, experience, args.data)
        spent, seed = spent + step, seed + 1
        growth = report["growth"]
        kept = ("held_for_review", "contradicted_edges", "new_nodes", "new_edges")
        rows.append(
            {
                "actions": spent,
                "refused": report["refused"],
                **table1(model, args.test, args.pairs),
                **{k: growth[k] for k in kept},
                "grow_seconds": growth["seconds"],
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    result: dict[str, Any] = {"rows": rows}
    if args.closed_loop:
        result["closed_loop"] = closed_loop(model, args.closed_loop)
    if args.figure:
        plot(rows, args.figure, args.label)
    return result


def run_loop(args: argparse.Namespace) -> dict[str, Any]:
    """Rounds of --loop-pairs ordinary tasks, each recording its experience and then growing
    the roadmap from it (as a deployment grows its model between shifts), until --budget
    actions (legal or refused) are spent (the last task cut short)."""
    model = copy_model(args.model, args.out)
    experience = args.out / "experience"
    shutil.rmtree(experience, ignore_errors=True)
    rows = [{"actions": 0, **table1(model, args.test, args.pairs)}]
    print(json.dumps(rows[-1]), flush=True)
    spent, seed = 0, args.seed + 1
    tried: set[tuple[int, int]] = set()  # shortcuts tried, remembered across versions
    while spent < args.budget:
        loop = closed_loop(
            model, args.loop_pairs, experience, seed, args.shortcuts, args.budget - spent, tried
        )
        tried_now = loop["actions_executed"] + loop["illegal_actions"]
        spent, seed = spent + tried_now, seed + 1
        row: dict[str, Any] = {"actions": spent, "closed_loop": loop}
        if not tried_now:  # every task ended before acting: stop rather than spin
            rows.append(row | {"stopped": "a round of tasks tried no action"})
            print(json.dumps(rows[-1]), flush=True)
            break
        growth = grow_model(model, [experience], args.data)
        row |= {k: growth[k] for k in ("new_nodes", "new_edges", "held_for_review")}
        rows.append(row | table1(model, args.test, args.pairs))
        print(json.dumps(rows[-1]), flush=True)
    return {"rows": rows}


def run_timing(args: argparse.Namespace) -> dict[str, Any]:
    """Members first (a v1 roadmap without them encodes its training data), then the growth."""
    from services.data.experience import ExperienceLog
    from services.encoder.checkpoint import load_vae
    from services.planner.grow import load_members
    from shared.dataset import load_dataset

    model = copy_model(args.model, args.out)
    vae, _ = load_vae(model / "vae")
    members = load_members(model, vae, args.data)
    members.save(roadmap_dir(model))  # as a roadmap built today keeps them
    data = load_dataset(args.experience)
    new = args.out / "new"
    shutil.rmtree(new, ignore_errors=True)
    log = ExperienceLog(new, data.spec, data.image_size)
    pick = np.arange(args.new) % len(data)
    log.append(data.image1[pick], data.image2[pick], data.u[pick], data.state1[pick],
               data.state2[pick])  # fmt: skip
    started = time.perf_counter()
    growth = grow_model(model, [new])
    return {
        "roadmap_tuples": len(members.a),
        "new_tuples": args.new,
        "seconds": time.perf_counter() - started,
        "grow_seconds": growth["seconds"],
    }


def plot(rows: list[dict[str, Any]], path: Path, label: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    spent = [r["actions"] for r in rows]
    fig, left = plt.subplots(figsize=(6.4, 3.6))
    left.plot(spent, [r["all"] for r in rows], "o-", color="tab:blue", label="All (%)")
    left.set_xlabel("actions spent exploring")
    left.set_ylabel("All: every shortest plan valid (%)", color="tab:blue")
    left.set_ylim(0, 101)
    right = left.twinx()
    right.plot(spent, [r["components"] for r in rows], "s--", color="tab:red")
    right.set_ylabel("roadmap components", color="tab:red")
    right.set_ylim(bottom=0)
    left.set_title(f"Exploration grows the roadmap, VAE fixed ({label})")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("mode", choices=["explore", "loop", "timing"])
    parser.add_argument("--model", required=True, type=Path)
    parser.add_argument("--test", type=Path, default=Path("data/box_stacking/test"))
    parser.add_argument("--out", required=True, type=Path)
    parser.add_argument("--data", type=Path, help="the model's training data (older roadmaps)")
    parser.add_argument("--pairs", type=int, default=1000, help="Table I test pairs")
    parser.add_argument("--budget", type=int, default=2000)
    parser.add_argument("--step", type=int, default=250)
    parser.add_argument("--looks", type=int, default=0, help="explore: looks after each action")
    parser.add_argument("--stop-at", type=float, default=101.0, help="stop once All reaches it")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--closed-loop", type=int, default=0, help="closed-loop tasks at the end")
    parser.add_argument("--loop-pairs", type=int, default=100, help="loop mode: tasks a round")
    parser.add_argument(
        "--shortcuts", type=float, default=0.0, help="loop mode: share of steps that skip a node"
    )
    parser.add_argument("--experience", type=Path, help="timing mode: tuples to grow from")
    parser.add_argument("--new", type=int, default=1000, help="timing mode: tuples to grow")
    parser.add_argument(
        "--threads", type=int, default=1, help="torch threads (0: all, as lsr roadmap grow)"
    )
    parser.add_argument("--figure", type=Path)
    parser.add_argument("--label", default="")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    args.out.mkdir(parents=True, exist_ok=True)
    run = {"explore": run_explore, "loop": run_loop, "timing": run_timing}[args.mode]
    result = {"mode": args.mode, "model": str(args.model), "threads": torch.get_num_threads()}
    result |= run(args)
    (args.out / "results.json").write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
