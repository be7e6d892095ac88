"""The `lsr` command line: one entry point for every part of the project."""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from shared.settings import SHIPPED_MODEL
from shared.tasks import get_task, task_names

Handler = Callable[[argparse.Namespace], int]


def _json_arg(text: str) -> Any:
    """JSON given inline, or the path of a JSON file."""
    source = Path(text).read_text() if not text.lstrip().startswith(("{", "[")) else text
    try:
        return json.loads(source)
    except json.JSONDecodeError as exc:
        raise ValueError(f"not valid JSON: {exc}") from None


def _robot_id_arg(text: str) -> str:
    from shared.bus import ROBOT_ID_PATTERN

    if not re.fullmatch(ROBOT_ID_PATTERN, text):
        raise argparse.ArgumentTypeError(
            f"{text!r} is not one zenoh key chunk: 1 to 128 characters, none of / * $ ? #, "
            "no control characters, not starting with @"
        )
    return text


def cmd_task_info(args: argparse.Namespace) -> int:
    print(json.dumps(get_task(args.task).info(), indent=2))
    return 0


def cmd_data_generate(args: argparse.Namespace) -> int:
    from services.sim.datagen import GenerateConfig, generate

    cfg = GenerateConfig(
        task=args.task,
        pairs=args.pairs,
        seed=args.seed,
        image_size=args.size,
        action_fraction=args.action_fraction,
        workers=args.workers,
        episode_length=args.episode_length,
    )
    result = generate(cfg, args.out, overwrite=args.overwrite)
    counts = result["counts"]
    print(
        f"wrote {counts['tuples']} tuples ({counts['action_pairs']} action, "
        f"{counts['no_action_pairs']} no-action) to {args.out} in {result['seconds']:.1f} s "
        f"({result['images_per_second']:.0f} images/s)"
    )
    return 0


def cmd_render(args: argparse.Namespace) -> int:
    import numpy as np
    from PIL import Image

    from services.sim.worlds import make_world

    task = get_task(args.task)
    state = task.parse_state(_json_arg(args.state))
    with make_world(args.task, args.size) as world:
        world.reset(state, np.random.default_rng(args.seed))
        Image.fromarray(world.render()).save(args.out)
    print(f"wrote {args.out}")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    """A contact sheet of rendered states: box stacking, five states and one executed move;
    cloth folding, the whole state family."""
    import numpy as np
    from PIL import Image

    from services.planner.sheets import describe
    from services.sim.worlds import make_world
    from shared.images import contact_sheet

    task = get_task(args.task)
    rng = np.random.default_rng(args.seed)
    states = task.all_states()
    images, labels = [], []
    with make_world(args.task, args.size) as world:
        if args.task == "box_stacking":
            picks = [states[i] for i in rng.choice(len(states), size=5, replace=False)]
            for state in picks:
                world.reset(state, rng)
                images.append(world.render())
                labels.append(" | ".join(",".join(b[0].upper() for b in c) or "-" for c in state))
            action = task.legal_actions(picks[-1])[0]
            world.execute(action, rng)
            what, columns = "5 rendered states and the last one after a move", 3
        else:
            picks = list(states)
            for state in picks:
                world.reset(state, rng)
                images.append(world.render())
                labels.append(" ".join("".join(w[0].upper() for w in f.split("_")) for f in state))
            action = task.legal_actions(picks[-1])[0]
            world.execute(world.demonstrated(action, rng), rng)
            what, columns = f"all {len(picks)} states and the last one after a move", 6
        images.append(world.render())
        labels.append(describe(action))
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(contact_sheet(images, columns=columns, labels=labels)).save(out)
    print(f"wrote {out}: {what}")
    return 0


def cmd_train_vae(args: argparse.Namespace) -> int:
    from services.encoder.train import TrainConfig, dm_from_baseline, train_vae
    from shared.dataset import load_dataset

    dm: float | None = None
    meta = {}
    if args.dm == "auto":
        if args.metric == "none":
            raise ValueError("--dm auto needs a metric other than none")
        if args.baseline is None:
            raise ValueError("--dm auto needs --baseline DIR, a VAE trained with --metric none")
        dm = dm_from_baseline(args.baseline, load_dataset(args.data), args.metric)
        meta["dm_auto"] = {"baseline": str(args.baseline), "value": dm}
        print(f"d_m from the baseline's mean action-pair distance: {dm:.3f}")
    elif args.dm is not None:
        dm = float(args.dm)
    cfg = TrainConfig(
        metric=args.metric,
        dm=dm,
        epochs=args.epochs,
        batch_size=args.batch_size,
        lr_drop_epoch=args.lr_drop_epoch,
        beta_max=args.beta_max,
        action_on=args.action_on,
        seed=args.seed,
        threads=args.threads,
    )
    record = train_vae(args.data, args.out, cfg, extra_meta=meta)
    print(json.dumps(record))
    return 0


def cmd_train_reader(args: argparse.Namespace) -> int:
    from services.sim.state_reader import load_reader, read_states, train_reader
    from shared.dataset import load_dataset

    meta = train_reader(load_dataset(args.data), args.out, epochs=args.epochs, seed=args.seed)
    print(f"trained in {meta['train']['seconds']:.0f} s on {meta['train']['images']} images")
    if args.test:
        from services.planner.eval_vfm import load_test_images

        images, states, _ = load_test_images(args.test)
        reads = read_states(load_reader(args.out), images)
        accuracy = 100.0 * float((reads == states).reshape(len(images), -1).all(1).mean())
        print(json.dumps({"test_images": len(images), "state_accuracy": accuracy}))
    return 0


def cmd_build_roadmap(args: argparse.Namespace) -> int:
    from services.encoder.checkpoint import read_vae_config
    from services.planner.build import build_from_dataset, default_metric
    from services.planner.roadmap import RoadmapConfig

    metric = args.metric or default_metric(read_vae_config(args.vae))
    config = RoadmapConfig(metric=metric, w_eps=args.w_eps, min_samples=args.min_samples)
    summary = build_from_dataset(args.vae, args.data, config, args.out)
    print(json.dumps(summary))
    return 0


def cmd_eval_vfm(args: argparse.Namespace) -> int:
    from services.planner.eval_vfm import run_vfm_eval
    from services.planner.evaluate import plot_class_distances

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


def cmd_train_apn(args: argparse.Namespace) -> int:
    from services.apn.train import APNTrainConfig, train_apn

    _single_thread_torch()  # a 7k-parameter MLP: threads only add overhead
    cfg = APNTrainConfig(head=args.head, epochs=args.epochs, samples=args.samples, seed=args.seed)
    meta = train_apn(args.vae, args.data, args.out, cfg)
    print(json.dumps({"best": meta["best"], "pairs": meta["pairs"], "seconds": meta["seconds"]}))
    return 0


def cmd_eval_apn(args: argparse.Namespace) -> int:
    from services.apn.train import evaluate_apn

    result = evaluate_apn(args.apn or args.model / "apn", args.model / "vae", args.test)
    if not args.json:
        for key, value in result.items():
            print(f"{key:>20}: {value}")
    print(json.dumps(result))
    return 0


def _image_or_state(task, world, image: Path | None, state: str | None, rng, name: str):
    """A start or goal given as a PNG/JPEG file or as a state rendered by the sim."""
    from shared.images import decode_image

    if (image is None) == (state is None):
        raise ValueError(f"give exactly one of --{name}-image and --{name}-state")
    if image is not None:
        return decode_image(Path(image).read_bytes(), size=world.image_size), None
    parsed = task.parse_state(_json_arg(state))
    world.reset(parsed, rng)
    return world.render(), parsed


def _single_thread_torch() -> None:
    """Plans run batches of a few images: one thread beats two that spin-wait on each other."""
    import torch

    torch.set_num_threads(1)


def cmd_plan(args: argparse.Namespace) -> int:
    import numpy as np
    from PIL import Image

    from services.planner.action_plans import ActionPlanner
    from services.planner.sheets import plan_sheet
    from services.sim.worlds import make_world

    _single_thread_torch()
    planner = ActionPlanner.from_model_dir(args.model)
    rng = np.random.default_rng(args.seed)
    with make_world(planner.task.name, planner.image_size) as world:
        start, _ = _image_or_state(
            planner.task, world, args.start_image, args.start_state, rng, "start"
        )
        goal, _ = _image_or_state(
            planner.task, world, args.goal_image, args.goal_state, rng, "goal"
        )
        plans = planner.plan(start, goal, max_plans=args.max_plans)
        args.out.mkdir(parents=True, exist_ok=True)
        for k, plan in enumerate(plans):
            sheet = plan_sheet(
                plan, world.action_pixels, arrows=bool(world.task.spec.action.pixels)
            )
            Image.fromarray(sheet).save(args.out / f"plan_{k}.png")
    summary = {"plans": [p.to_json(planner.task) for p in plans]}
    if not plans:
        summary["reason"] = "start and goal are not connected in the roadmap"
    (args.out / "plans.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(f"{len(plans)} plan(s) written to {args.out}")
    return 0


def cmd_eval_system(args: argparse.Namespace) -> int:
    from services.planner.action_plans import ActionPlanner
    from services.planner.build import load_labels
    from services.sim.closed_loop import PlanJudge, evaluate_system
    from services.sim.worlds import make_world

    _single_thread_torch()
    planner = ActionPlanner.from_model_dir(args.model)
    labels = load_labels(Path(args.model) / "roadmap", planner.task.name)
    task = planner.task
    judge = PlanJudge(task, [task.array_to_state(s) for s in labels.states])
    with make_world(task.name, planner.image_size) as world:
        result = evaluate_system(
            planner, world, task, args.pairs, seed=args.seed, max_steps=args.max_steps, judge=judge
        )
    if not args.json:
        for key, value in result.items():
            print(f"{key:>20}: {value}")
    print(json.dumps(result))
    return 0


def _settings(**fields: Any):
    """Environment settings (LSR_*) with the flags that were given on top."""
    from shared.settings import Settings

    given = {k: v for k, v in fields.items() if v is not None}
    return Settings(**given)


def cmd_serve(args: argparse.Namespace) -> int:
    from services.serve import serve_gateway, serve_service

    settings = _settings(
        zenoh_connect=args.connect,
        model_dir=args.model,
        instance=args.instance,
        host=args.host,
        port=args.port,
    )
    if args.service == "gateway":
        return serve_gateway(settings)
    return serve_service(args.service, settings)


def cmd_router(args: argparse.Namespace) -> int:
    from services.serve import serve_router

    return serve_router(args.listen)


def cmd_ping(args: argparse.Namespace) -> int:
    from services.serve import ping

    settings = _settings(zenoh_connect=args.connect)
    return ping(args.service, settings, args.this_host, args.timeout)


def cmd_up(args: argparse.Namespace) -> int:
    from services.stack import StackConfig, run_up

    config = StackConfig(
        host=args.host, port=args.port, zenoh_port=args.zenoh_port, model_dir=args.model
    )
    return run_up(config)


def cmd_robot(args: argparse.Namespace) -> int:
    from services.robot import run_robot
    from shared.bus import close_quietly, open_session

    task = get_task(args.task)
    start = task.parse_state(_json_arg(args.start_state))
    goal = task.parse_state(_json_arg(args.goal_state))
    config = _settings(zenoh_connect=args.connect).bus()
    config.open_timeout_s = 10.0
    session = open_session(config)
    try:
        episode = run_robot(
            session, args.robot_id, args.task, start, goal, args.max_steps, args.seed
        )
    finally:
        close_quietly(session)
    outcome = "reached the goal" if episode.success else f"stopped: {episode.reason}"
    print(f"[{args.robot_id}] {outcome} after {len(episode.actions)} actions")
    return 0 if episode.success else 1


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="lsr", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)

    task = sub.add_parser("task", help="task descriptions").add_subparsers(
        dest="sub", required=True
    )
    info = task.add_parser("info", help="print a task's description as JSON")
    info.add_argument("task", choices=task_names())
    info.set_defaults(handler=cmd_task_info)

    data = sub.add_parser("data", help="datasets").add_subparsers(dest="sub", required=True)
    gen = data.add_parser("generate", help="render a dataset of action and no-action pairs")
    gen.add_argument("--task", default="box_stacking", choices=task_names())
    gen.add_argument("--pairs", type=int, default=5000, help="number of tuples")
    gen.add_argument("--seed", type=int, default=0)
    gen.add_argument("--size", type=int, default=64, help="image size in pixels (square)")
    gen.add_argument("--action-fraction", type=float, default=0.65)
    gen.add_argument("--workers", type=int, default=2, help="rendering processes")
    gen.add_argument(
        "--episode-length",
        type=int,
        default=None,
        help="tuples walked from one reset (default: the world's, 1 box stacking, 10 cloth)",
    )
    gen.add_argument("--out", required=True, type=Path)
    gen.add_argument("--overwrite", action="store_true", help="replace an existing folder")
    gen.set_defaults(handler=cmd_data_generate)

    train = sub.add_parser("train", help="train models").add_subparsers(dest="sub", required=True)
    vae = train.add_parser("vae", help="train the action-VAE (metric none = baseline VAE-b)")
    vae.add_argument("--data", required=True, type=Path, help="training dataset folder")
    vae.add_argument("--metric", default="l1", choices=["l1", "l2", "inf", "none"])
    vae.add_argument("--out", required=True, type=Path)
    vae.add_argument(
        "--dm",
        default=None,
        help="action margin d_m: a number, or auto "
        "(mean action-pair distance under --baseline); default: the paper's value",
    )
    vae.add_argument("--baseline", type=Path, help="VAE-b folder, for --dm auto")
    vae.add_argument("--epochs", type=int, default=30)
    vae.add_argument("--batch-size", type=int, default=64)
    vae.add_argument("--lr-drop-epoch", type=int, default=20)
    vae.add_argument("--beta-max", type=float, default=1.0)
    vae.add_argument(
        "--action-on",
        default="sample",
        choices=["sample", "mean"],
        help="latents the action term sees: reparameterised samples or means",
    )
    vae.add_argument("--seed", type=int, default=0)
    vae.add_argument("--threads", type=int, default=2)
    vae.set_defaults(handler=cmd_train_vae)

    reader = train.add_parser("reader", help="train the image -> state reader used by evals")
    reader.add_argument("--data", required=True, type=Path)
    reader.add_argument("--out", required=True, type=Path)
    reader.add_argument("--test", type=Path, help="test set to report accuracy on")
    reader.add_argument("--epochs", type=int, default=8)
    reader.add_argument("--seed", type=int, default=0)
    reader.set_defaults(handler=cmd_train_reader)

    apn = train.add_parser("apn", help="train the Action Proposal Network on a VAE's latents")
    apn.add_argument("--vae", required=True, type=Path)
    apn.add_argument("--data", required=True, type=Path)
    apn.add_argument("--out", required=True, type=Path)
    apn.add_argument(
        "--head",
        default=None,
        choices=["classify", "regress", "hybrid"],
        help="default: classify small ranges; hybrid (pixels regressed) for pixel actions",
    )
    apn.add_argument("--epochs", type=int, default=200)
    apn.add_argument("--samples", type=int, default=1, help="S draws from q(z|I) per pair")
    apn.add_argument("--seed", type=int, default=0)
    apn.set_defaults(handler=cmd_train_apn)

    roadmap = sub.add_parser("build-roadmap", help="build the Latent Space Roadmap of a VAE")
    roadmap.add_argument("--vae", required=True, type=Path)
    roadmap.add_argument("--data", required=True, type=Path, help="training dataset folder")
    roadmap.add_argument("--w-eps", type=float, default=1.0)
    roadmap.add_argument("--min-samples", type=int, default=3)
    roadmap.add_argument(
        "--metric",
        choices=["l1", "l2", "inf"],
        help="default: the VAE's training metric (l1 for the baseline)",
    )
    roadmap.add_argument("--out", required=True, type=Path)
    roadmap.set_defaults(handler=cmd_build_roadmap)

    evals = sub.add_parser("eval", help="evaluations").add_subparsers(dest="sub", required=True)
    vfm = evals.add_parser("vfm", help="Table I: plans between unseen test images")
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

    eapn = evals.add_parser("apn", help="APN accuracy on unseen action pairs")
    eapn.add_argument("--model", required=True, type=Path, help="folder with vae/ and apn/")
    eapn.add_argument("--apn", type=Path, help="APN folder (default: MODEL/apn)")
    eapn.add_argument("--test", required=True, type=Path)
    eapn.add_argument("--json", action="store_true")
    eapn.set_defaults(handler=cmd_eval_apn)

    system = evals.add_parser("system", help="closed-loop execution in simulation")
    system.add_argument("--model", type=Path, default=Path("models/box_stacking"))
    system.add_argument("--pairs", type=int, default=1000)
    system.add_argument("--seed", type=int, default=0)
    system.add_argument("--max-steps", type=int, default=20)
    system.add_argument("--json", action="store_true")
    system.set_defaults(handler=cmd_eval_system)

    plan = sub.add_parser("plan", help="visual action plans from a start to a goal")
    plan.add_argument("--model", type=Path, default=Path("models/box_stacking"))
    plan.add_argument("--start-state", help="state JSON, inline or a file path")
    plan.add_argument("--start-image", type=Path, help="PNG or JPEG of the start")
    plan.add_argument("--goal-state", help="state JSON, inline or a file path")
    plan.add_argument("--goal-image", type=Path, help="PNG or JPEG of the goal")
    plan.add_argument("--max-plans", type=int, default=4)
    plan.add_argument("--seed", type=int, default=0, help="noise of rendered states")
    plan.add_argument("--out", required=True, type=Path)
    plan.set_defaults(handler=cmd_plan)

    render = sub.add_parser("render", help="render one state to a PNG")
    render.add_argument("--task", default="box_stacking", choices=task_names())
    render.add_argument("--state", required=True, help="state JSON, inline or a file path")
    render.add_argument("--seed", type=int, default=0)
    render.add_argument("--size", type=int, default=64)
    render.add_argument("--out", required=True, type=Path)
    render.set_defaults(handler=cmd_render)

    demo = sub.add_parser("demo", help="render a contact sheet of a few states")
    demo.add_argument("--task", default="box_stacking", choices=task_names())
    demo.add_argument("--out", type=Path, default=Path("docs/images/box_stacking_states.png"))
    demo.add_argument("--size", type=int, default=128)
    demo.add_argument("--seed", type=int, default=0)
    demo.set_defaults(handler=cmd_demo)
    serve = sub.add_parser("serve", help="run one service (or the gateway) until SIGINT/SIGTERM")
    serve.add_argument("service", choices=["encoder", "planner", "apn", "sim", "gateway"])
    serve.add_argument("--model", type=Path, help="model folder (env LSR_MODEL_DIR)")
    serve.add_argument("--connect", help="zenoh router endpoints (env LSR_ZENOH_CONNECT)")
    serve.add_argument("--instance", help="instance id (default hostname-pid-random)")
    serve.add_argument("--host", help="gateway: address to bind (env LSR_HOST)")
    serve.add_argument("--port", type=int, help="gateway: port (env LSR_PORT)")
    serve.set_defaults(handler=cmd_serve)

    router = sub.add_parser("router", help="a zenoh router (a Python session in router mode)")
    router.add_argument("--listen", nargs="+", default=["tcp/127.0.0.1:7447"])
    router.set_defaults(handler=cmd_router)

    ping = sub.add_parser("ping", help="exit 0 when a service answers (container health check)")
    ping.add_argument("service", choices=["encoder", "planner", "apn", "sim"])
    ping.add_argument("--this-host", action="store_true", help="only instances on this host")
    ping.add_argument("--connect", help="zenoh router endpoints (env LSR_ZENOH_CONNECT)")
    ping.add_argument("--timeout", type=float, default=2.0)
    ping.set_defaults(handler=cmd_ping)

    up = sub.add_parser("up", help="start the whole stack on loopback; Ctrl-C stops it")
    up.add_argument("--host", default="127.0.0.1")
    up.add_argument("--port", type=int, default=8000)
    up.add_argument("--zenoh-port", type=int, default=7447)
    up.add_argument("--model", type=Path, default=SHIPPED_MODEL, help="default: the shipped one")
    up.set_defaults(handler=cmd_up)

    robot = sub.add_parser("robot", help="an example robot: plans over zenoh, acts in its sim")
    robot.add_argument("--robot-id", required=True, type=_robot_id_arg)
    robot.add_argument("--task", default="box_stacking", choices=task_names())
    robot.add_argument("--start-state", required=True, help="state JSON, inline or a file path")
    robot.add_argument("--goal-state", required=True, help="state JSON, inline or a file path")
    robot.add_argument("--max-steps", type=int, default=20)
    robot.add_argument("--seed", type=int, default=0)
    robot.add_argument("--connect", help="zenoh router endpoints (env LSR_ZENOH_CONNECT)")
    robot.set_defaults(handler=cmd_robot)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    handler: Handler = args.handler
    try:
        return handler(args)
    except (ValueError, FileExistsError, FileNotFoundError, NotImplementedError) as exc:
        print(f"lsr: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
