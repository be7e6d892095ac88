"""`lsr train`: a whole model from a dataset, or its parts (the action-VAE, the APN) and the
state reader."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from services.cli.common import dataset_setting, single_thread_torch

AUGMENT_HELP = "the encoder sees each image under a drawn look (exposure, colour, noise, shift)"


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
    else:  # a task defined by its data may set its own (task.json's settings.d_m)
        dm = dataset_setting(args.data, "d_m")
        if dm is not None:
            print(f"d_m {dm} from the dataset's task.json settings")
    lr_drop = args.lr_drop
    if args.lr_drop_epoch is not None:
        if args.epochs is None:
            raise ValueError("--lr-drop-epoch needs --epochs; with --steps use --lr-drop")
        lr_drop = args.lr_drop_epoch / args.epochs
    cfg = TrainConfig(
        metric=args.metric,
        dm=dm,
        **({"steps": args.steps} if args.steps is not None else {}),
        epochs=args.epochs,
        batch_size=args.batch_size,
        lr_drop=lr_drop,
        beta_max=args.beta_max,
        clip_grad_norm=args.clip_grad_norm,
        action_on=args.action_on,
        augment=args.augment,
        seed=args.seed,
        threads=args.threads,
        device=args.device,
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


def cmd_train_apn(args: argparse.Namespace) -> int:
    from services.apn.train import APNTrainConfig, train_apn

    single_thread_torch()  # a 7k-parameter MLP: threads only add overhead
    cfg = APNTrainConfig(
        head=args.head,
        **({"steps": args.steps} if args.steps is not None else {}),
        epochs=args.epochs,
        samples=args.samples,
        seed=args.seed,
        restarts=args.restarts,
        undo=not args.no_undo,
        device=args.device,
    )
    meta = train_apn(args.vae, args.data, args.out, cfg, roadmap_dir=args.roadmap)
    print(json.dumps({"best": meta["best"], "pairs": meta["pairs"], "seconds": meta["seconds"]}))
    return 0


def cmd_train_model(args: argparse.Namespace) -> int:
    from services.recipe import APN_RESTARTS, Recipe, train_model

    recipe = Recipe(
        metric=args.metric,
        seed=args.seed,
        device=args.device,
        vae_steps=args.vae_steps,
        eps_rule=args.eps_rule,
        w_eps=args.w_eps,
        min_samples=args.min_samples,
        apn_steps=args.apn_steps,
        apn_restarts=args.apn_restarts or APN_RESTARTS,
        vae=args.vae,
        augment=args.augment,
    )
    figures = train_model(args.data, args.out, recipe, overwrite=args.overwrite)
    print(
        f"{args.out}: {figures['nodes']} nodes, {figures['edges']} edges, epsilon "
        f"{figures['epsilon']:.3g}, {100 * figures['known_training_images']:.2f}% of the "
        f"training images known, {figures['seconds'] / 60:.1f} min; serve it with "
        f"lsr up --model {args.out}"
    )
    if args.json:
        print(json.dumps(figures))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    train = sub.add_parser("train", help="train models").add_subparsers(dest="sub", required=True)
    model = train.add_parser(
        "model",
        help="a whole model (VAE, roadmap, knowing, APN) from one dataset, every setting "
        "chosen from the dataset",
    )
    model.add_argument("--data", required=True, type=Path, help="training dataset folder")
    model.add_argument("--out", required=True, type=Path, help="model folder to write")
    model.add_argument("--metric", default="l1", choices=["l1", "l2", "inf", "none"])
    model.add_argument("--seed", type=int, default=0)
    model.add_argument("--device", default="auto", help="auto (CUDA when present), cpu or cuda")
    model.add_argument("--json", action="store_true", help="the figures as JSON, last line")
    model.add_argument("--overwrite", action="store_true", help="replace a model already in OUT")
    model.add_argument(
        "--vae",
        type=Path,
        help="a VAE trained on this dataset before (a model's, or one kept in OUT.partial): "
        "build the roadmap and train the APN only, in its metric",
    )
    research = model.add_argument_group("research (never needed: chosen from the dataset)")
    research.add_argument("--vae-steps", type=int)
    research.add_argument("--eps-rule", choices=["stable", "paper"])
    research.add_argument("--w-eps", type=float)
    research.add_argument("--min-samples", type=int)
    research.add_argument("--apn-steps", type=int)
    research.add_argument("--apn-restarts", type=int, help="default 5")
    research.add_argument("--augment", action="store_true", help=AUGMENT_HELP)
    model.set_defaults(handler=cmd_train_model)

    vae = train.add_parser("vae", help="train the action-VAE (metric none = baseline VAE-b)")
    vae.add_argument("--data", required=True, type=Path, help="training dataset folder")
    vae.add_argument("--metric", default="l1", choices=["l1", "l2", "inf", "none"])
    vae.add_argument("--out", required=True, type=Path)
    vae.add_argument(
        "--dm",
        default=None,
        help="action margin d_m: a number, or auto "
        "(mean action-pair distance under --baseline); default: the dataset's task.json "
        "settings.d_m, else the paper's value",
    )
    vae.add_argument("--baseline", type=Path, help="VAE-b folder, for --dm auto")
    length = vae.add_mutually_exclusive_group()
    length.add_argument(
        "--steps",
        type=int,
        help="optimiser steps, whatever the dataset's size "
        "(default: services.encoder.train.DEFAULT_STEPS, 2400)",
    )
    length.add_argument("--epochs", type=int, help="passes over the data instead of --steps")
    vae.add_argument("--batch-size", type=int, default=64)
    vae.add_argument(
        "--lr-drop", type=float, default=2 / 3, help="fraction of the run after which lr / 10"
    )
    vae.add_argument("--lr-drop-epoch", type=int, help="with --epochs: the epoch of the lr drop")
    vae.add_argument("--beta-max", type=float, default=1.0)
    vae.add_argument(
        "--clip-grad-norm", type=float, default=1000.0, help="inf: no clipping (the shipped models)"
    )
    vae.add_argument(
        "--action-on",
        default="sample",
        choices=["sample", "mean"],
        help="latents the action term sees: reparameterised samples or means",
    )
    vae.add_argument("--augment", action="store_true", help=AUGMENT_HELP)
    vae.add_argument("--seed", type=int, default=0)
    vae.add_argument("--threads", type=int, default=2)
    vae.add_argument("--device", default="auto", help="auto (CUDA when present), cpu or cuda")
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
    apn.add_argument(
        "--data",
        required=True,
        type=Path,
        nargs="+",
        help="training dataset, then any experience folders whose action pairs it learns too",
    )
    apn.add_argument("--out", required=True, type=Path)
    apn.add_argument(
        "--roadmap",
        type=Path,
        help="a roadmap built on this VAE (lsr build-roadmap --out): its demonstrated edges, as "
        "the nodes' latents plans ask about, join the training split (lsr train model does so)",
    )
    apn.add_argument(
        "--head",
        default=None,
        choices=["classify", "regress", "hybrid"],
        help="default: classify small ranges; hybrid (pixels regressed) for pixel actions",
    )
    length = apn.add_mutually_exclusive_group()
    length.add_argument(
        "--steps",
        type=int,
        help="optimiser steps, whatever the dataset's size "
        "(default: services.apn.train.DEFAULT_STEPS, 8000)",
    )
    length.add_argument(
        "--epochs", type=int, help="passes over the data instead (the shipped models: 200)"
    )
    apn.add_argument("--samples", type=int, default=1, help="S draws from q(z|I) per pair")
    apn.add_argument("--seed", type=int, default=0)
    apn.add_argument(
        "--restarts",
        type=int,
        default=1,
        help="runs from fresh weights (seeds SEED, SEED+1, ...) on one validation split; "
        "the lowest validation loss is kept",
    )
    apn.add_argument(
        "--no-undo",
        action="store_true",
        help="train on the demonstrated direction only, even where the task declares how a "
        "move is undone (spec 'undo')",
    )
    apn.add_argument("--device", default="auto", help="auto (CUDA when present), cpu or cuda")
    apn.set_defaults(handler=cmd_train_apn)
