"""`lsr eval`: the paper's tables, measured."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from services.cli.common import single_thread_torch
from services.planner.versions import roadmap_dir
from shared.appearance import LEVELS, levels_help
from shared.settings import SHIPPED_MODEL


def cmd_eval_vfm(args: argparse.Namespace) -> int:
    from services.encoder.checkpoint import read_vae_config
    from services.planner.eval_vfm import run_vfm_eval
    from services.planner.evaluate import plot_class_distances

    spec = read_vae_config(args.model / "vae")["dataset"].get("spec")
    if spec is not None and spec.get("state") is None:  # a task defined by its data
        from services.planner.eval_data import run_data_eval

        row = run_data_eval(
            args.model, args.test, args.pairs, args.seed, args.max_paths, train_dir=args.train
        )
        if not args.json:
            for key, value in row.items():
                print(f"{key:>32}: {value}")
        print(json.dumps(row))
        return 0
    reader = args.reader or (args.model / "state_reader")
    row, analysis = run_vfm_eval(
        args.model,
        args.test,
        pairs=args.pairs,
        seed=args.seed,
        max_paths=args.max_paths,
        reader_dir=reader if reader.is_dir() else None,
        train_dir=args.train,
    )
    if args.figure and analysis is not None:
        plot_class_distances({args.model.name: analysis}, args.figure)
    if not args.json:
        for key, value in row.items():
            print(f"{key:>32}: {value}")
    print(json.dumps(row))
    return 0


def cmd_eval_apn(args: argparse.Namespace) -> int:
    from services.apn.train import evaluate_apn

    apn_dir = args.apn or args.model / "apn"
    result = evaluate_apn(apn_dir, args.model / "vae", args.test)
    if (roadmap_dir(args.model) / "labels.json").is_file():  # a task with states and rules
        from services.planner.action_plans import model_edge_actions

        result["roadmap_edges"] = model_edge_actions(args.model, apn_dir)
    if not args.json:
        for key, value in result.items():
            print(f"{key:>20}: {value}")
    print(json.dumps(result))
    return 0


def cmd_eval_system(args: argparse.Namespace) -> int:
    from services.encoder.checkpoint import read_vae_config
    from services.planner.action_plans import ActionPlanner
    from services.planner.build import load_labels
    from services.sim.closed_loop import PlanJudge, evaluate_system
    from services.sim.worlds import make_world
    from shared.appearance import trained_appearance
    from shared.tasks import has_simulator

    single_thread_torch()
    planner = ActionPlanner.from_model_dir(args.model)
    if not has_simulator(planner.task.name):
        raise ValueError(
            f"task {planner.task.name!r} has no simulator (it is defined by its data): "
            "lsr eval system needs one; lsr eval vfm and lsr eval apn need none"
        )
    labels = load_labels(roadmap_dir(args.model), planner.task.name)
    task = planner.task
    judge = PlanJudge(task, [task.array_to_state(s) for s in labels.states])
    appearance = args.appearance or trained_appearance(read_vae_config(Path(args.model) / "vae"))
    record = None
    if args.experience is not None:
        from services.data.experience import ExperienceLog, Recorder

        record = Recorder(ExperienceLog(args.experience, task.spec, planner.image_size), task)
    with make_world(task.name, planner.image_size, appearance=appearance) as world:
        result = evaluate_system(
            planner,
            world,
            task,
            args.pairs,
            seed=args.seed,
            max_steps=args.max_steps,
            judge=judge,
            record=record,
            head_camera=args.head_camera,
        )
    result["appearance"] = appearance
    result["head_camera"] = args.head_camera
    if not args.json:
        for key, value in result.items():
            print(f"{key:>20}: {value}")
    print(json.dumps(result))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    evals = sub.add_parser("eval", help="evaluations").add_subparsers(dest="sub", required=True)
    vfm = evals.add_parser(
        "vfm",
        help="Table I: plans between unseen test images (without state labels for a task "
        "defined by its data: roadmap size, nodes per episode, test images held by their node)",
    )
    vfm.add_argument("--model", required=True, type=Path, help="folder with vae/ and roadmap/")
    vfm.add_argument("--test", required=True, type=Path)
    vfm.add_argument("--pairs", type=int, default=1000)
    vfm.add_argument("--seed", type=int, default=0)
    vfm.add_argument("--max-paths", type=int, default=1000)
    vfm.add_argument("--reader", type=Path, help="default: MODEL/state_reader when present")
    vfm.add_argument(
        "--train",
        type=Path,
        help="training set for the class-distance analysis "
        "(default: the VAE's recorded training set, when present)",
    )
    vfm.add_argument("--figure", type=Path, help="PNG of the class-distance analysis")
    vfm.add_argument("--json", action="store_true", help="print only the JSON line")
    vfm.set_defaults(handler=cmd_eval_vfm)

    eapn = evals.add_parser(
        "apn", help="APN accuracy on unseen action pairs and on the roadmap's edges"
    )
    eapn.add_argument("--model", required=True, type=Path, help="folder with vae/ and apn/")
    eapn.add_argument("--apn", type=Path, help="APN folder (default: MODEL/apn)")
    eapn.add_argument("--test", required=True, type=Path)
    eapn.add_argument("--json", action="store_true")
    eapn.set_defaults(handler=cmd_eval_apn)

    system = evals.add_parser("system", help="closed-loop execution in simulation")
    system.add_argument(
        "--model",
        type=Path,
        default=SHIPPED_MODEL,
        help="model folder (default: the shipped box-stacking model, wherever lsr is run from)",
    )
    system.add_argument("--pairs", type=int, default=1000)
    system.add_argument("--seed", type=int, default=0)
    system.add_argument("--max-steps", type=int, default=20)
    system.add_argument(
        "--appearance",
        choices=LEVELS,
        help=f"how the simulated camera sees (default: the model's training data's; "
        f"{levels_help()})",
    )
    system.add_argument(
        "--experience",
        type=Path,
        help="record every executed action here, for lsr roadmap grow",
    )
    system.add_argument(
        "--head-camera",
        action="store_true",
        help="the camera's pose drawn anew for every image of an episode (a robot's head "
        "camera), within the look's ranges",
    )
    system.add_argument("--json", action="store_true")
    system.set_defaults(handler=cmd_eval_system)
