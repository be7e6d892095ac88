"""The data a cell must record: what `lsr train model` gives, with no flags, against the number of
recorded tuples, beside the LSR family's published points.

For each size: `lsr data generate` at the task's look (`camera` by default: registered camera
frames, look pairs by default), `lsr train model`, then on unseen test data Table I with refusals
counted (`lsr eval vfm`: `refusal_on`), the share of test images known, the APN
(`lsr eval apn`) and the closed loop in simulation (`lsr eval system`). With `--explore N` the
same model is grown by N of the arm's own actions (`lsr explore`) and measured again; with
`--train-apn` that model with its APN trained again on the recorded and explored moves (`lsr
train apn`), with `--retrain` a model trained again on the recorded and explored tuples (`lsr
data merge`). Exploration looks again `--looks` times after each executed action (recorded as
no-action pairs; 0, `lsr explore`'s default, keeps the names without `_l1`).
Each point's record is kept in OUT/SIZE/seedS/record.json (what it holds is not run again:
delete it to redo; a model that finished training before an interruption is kept too); data
seed = --seed + size + 100000 x training seed, so every point has data of its own. Prints a row
per point, writes OUT/RESULTS.json, puts each finished point into the task's measured points in
the repository (`--kept`, benchmarks/results/data_curves_TASK.json: a run folder does not
outlive its machine) and, with --figure, draws the curves of the kept points (at a size where
some were recorded with today's episode length, only those; `--figure` with no `--sizes` draws
them again).

Usage:
  python benchmarks/data_curves.py --task box_stacking --sizes 250 500 1000 2500 5000 \
      --out runs/curves_box --figure docs/images/data_curves_box_stacking.png
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
LSR = [sys.executable, "-m", "services.cli"]
# The LSR family's published points (../shared/reference/lsr-notes.md, "data budgets"):
# (label, tuples, %), Table I's all-correct queries or closed-loop runs as each paper reports.
FAMILY: dict[str, list[tuple[str, list[int], list[float]]]] = {
    "box_stacking": [
        ("LSR (paper): Table I All", [5000], [100.0]),
        ("LSR-v2 normal stacking: all plans right", [2500], [100.0]),
        ("ACE hard stacking: all plans right", [750, 1000, 1250], [51.5, 76.5, 82.6]),
    ],
    "tshirt_folding": [
        ("LSR-v2 real shirt: runs folded", [1283], [96.0]),
        ("ACE real shirt: runs folded", [575], [80.0]),
        ("plain LSR, same data: runs folded", [575], [44.0]),
        ("Ensemble LSR real shirt: runs folded", [562], [88.0]),
    ],
    "cloth_folding": [],
    "rope_box": [("LSR-v2 rope-box: all plans right", [2500], [89.7])],
}


def _cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def lsr(args: list[str], times: dict[str, Any], name: str) -> dict[str, Any]:
    """Run one `lsr` command; its last line as JSON; wall and CPU seconds into `times`."""
    print(f"  {name}: lsr {' '.join(args)}", flush=True)
    wall, cpu = time.perf_counter(), _cpu()
    result = subprocess.run([*LSR, *args], cwd=ROOT, capture_output=True, text=True)
    if result.returncode:
        sys.exit(f"{name} failed:\n{result.stderr[-3000:]}")
    times[name] = {"wall": time.perf_counter() - wall, "cpu": _cpu() - cpu}
    lines = result.stdout.strip().splitlines()
    return json.loads(lines[-1]) if lines and lines[-1].startswith("{") else {}


def measure(args: argparse.Namespace, model: Path, test: Path, times: dict[str, Any], tag: str):
    """Table I with refusals counted, images known, APN and closed loop of one model."""
    vfm = lsr(["eval", "vfm", "--model", str(model), "--test", str(test), "--pairs",
               str(args.test_pairs), "--json"], times, f"eval_vfm{tag}")  # fmt: skip
    out = {
        "nodes": vfm["nodes"],
        "edges": vfm["edges"],
        "table1": [vfm["all"], vfm["any"], vfm["trans"]],
        "table1_refusals_counted": [vfm["refusal_on"][k] for k in ("all", "any")]
        if "refusal_on" in vfm
        else None,
        "known_images": vfm.get("known_images"),
    }
    apn = lsr(["eval", "apn", "--model", str(model), "--test", str(test), "--json"], times,
              f"eval_apn{tag}")  # fmt: skip
    out["apn_right"] = apn.get("same_move", apn.get("both"))
    if args.closed_loop:
        tasks = ["--pairs", str(args.closed_loop), "--seed", str(args.loop_seed)]
        loop = lsr(["eval", "system", "--model", str(model), *tasks, "--json"], times,
                   f"closed_loop{tag}")  # fmt: skip
        out["closed_loop"] = loop.get("success")
    return out


def run_point(args: argparse.Namespace, pairs: int, seed: int, test: Path) -> dict[str, Any]:
    """One point; what its record.json holds already is kept and only what is missing runs."""
    run = args.out / f"{pairs}" / f"seed{seed}"
    path = run / "record.json"
    data_seed = args.seed + pairs + 100000 * seed
    record: dict[str, Any] = {"tuples": pairs, "seed": seed, "data_seed": data_seed}
    if path.exists():
        record = json.loads(path.read_text())
    test_seed = json.loads((test / "manifest.json").read_text()).get("seed")
    record |= {"appearance": args.appearance, "test_seed": test_seed}
    times: dict[str, Any] = record.setdefault("times", {})
    data, model = run / "train", run / "model"

    def save() -> None:  # after each stage: an interrupted run keeps what it measured
        run.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(record, indent=1) + "\n")

    if "defaults" not in record:
        if not (data / "manifest.json").exists():
            length = ["--episode-length", str(args.episode_length)] if args.episode_length else []
            lsr(["data", "generate", "--task", args.task, "--pairs", str(pairs), "--seed",
                 str(data_seed), "--appearance", args.appearance, "--overwrite", "--out",
                 str(data), *length], times, "generate")  # fmt: skip
        config = json.loads((data / "manifest.json").read_text())["config"]
        record["episode_length"] = config["episode_length"]
        record["trained"] = train(model, data, seed, times, "train_model")
        record["defaults"] = measure(args, model, test, times, "")
        save()
    explored, taught, retrained = kinds(args.looks)
    tag = explored.removeprefix("explored")
    grown = run / explored
    experience = grown / "experience" / "explore"
    if args.explore and explored not in record:
        shutil.rmtree(grown, ignore_errors=True)
        shutil.copytree(model, grown)
        lsr(["explore", "--model", str(grown), "--actions", str(args.explore), "--seed",
             str(data_seed), "--looks", str(args.looks)], times, "explore" + tag)  # fmt: skip
        record[explored] = measure(args, grown, test, times, "_" + explored)
        save()
    if args.train_apn and explored in record and taught not in record:
        # the grown roadmap, and the APN trained again on the recording and the explored moves
        apn = run / taught
        shutil.rmtree(apn, ignore_errors=True)
        shutil.copytree(grown, apn, ignore=shutil.ignore_patterns("apn"))
        lsr(["train", "apn", "--vae", str(apn / "vae"), "--data", str(data), str(experience),
             "--roadmap", str(apn / "roadmap"), "--out", str(apn / "apn"), "--seed",
             str(seed)], times, "train_" + taught)  # fmt: skip
        record[taught] = measure(args, apn, test, times, "_" + taught)
        save()
    if args.retrain and explored in record and retrained not in record:
        merged, again = run / ("merged" + tag), run / retrained
        lsr(["data", "merge", "--data", str(data), "--data", str(experience), "--overwrite",
             "--out", str(merged)], times, "merge" + tag)  # fmt: skip
        record[retrained + "_model"] = train(again, merged, seed, times, "train_model_" + retrained)
        record[retrained] = measure(args, again, test, times, "_" + retrained)
        save()
    return record


def kinds(looks: int) -> tuple[str, str, str]:
    """A point's record keys (and folders) for a model grown by exploring, that with its APN
    trained again, and one trained again on everything: by the looks taken after each action
    (0: the names of the first runs)."""
    tag = f"_l{looks}" if looks else ""
    return f"explored{tag}", f"explored{tag}_apn", f"retrained{tag}"


def train(model: Path, data: Path, seed: int, times: dict[str, Any], name: str) -> dict[str, Any]:
    """`lsr train model`; a model that finished training before an interrupted run is kept."""
    if (model / "recipe.json").exists():
        trained = json.loads((model / "recipe.json").read_text())["figures"]
        times[name] = {"wall": trained["seconds"], "cpu": None}
        return trained
    shutil.rmtree(model, ignore_errors=True)
    return lsr(["train", "model", "--data", str(data), "--out", str(model), "--seed", str(seed),
                "--json"], times, name)  # fmt: skip


def keep(path: Path, record: dict[str, Any]) -> None:
    """`record` into the kept points at `path`, in place of one with its size, data seed, look
    and episode length; written whole to a temporary file first, so that a killed run leaves
    the old one."""
    points = json.loads(path.read_text()) if path.exists() else []
    key = _key(record)
    points = [p for p in points if _key(p) != key] + [record]
    points.sort(key=lambda p: (p["tuples"], p["seed"], p["data_seed"], _key(p)[3] or 0))
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_suffix(".partial")
    partial.write_text(json.dumps(points, indent=1) + "\n")
    partial.replace(path)


def _key(record: dict[str, Any]) -> tuple[int, int, str, int | None]:
    look = record.get("appearance", "camera")
    return record["tuples"], record["data_seed"], look, record.get("episode_length")


def mean_by_size(points: list[dict[str, Any]], kind: str, key: str, index: int | None = None):
    """(sizes, the mean over training seeds of record[kind][key] (its [index]) at each)."""
    sizes = sorted({r["tuples"] for r in points})
    means = []
    for size in sizes:
        values = [r[kind].get(key) for r in points if r["tuples"] == size]
        values = [v if index is None else v[index] for v in values if v is not None]
        means.append(sum(values) / len(values) if values else float("nan"))
    return sizes, means


def recorded_today(task: str, records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The points whose recordings `lsr data generate` would make today (its episode length
    for their size), at each size where there are any; elsewhere every point there is."""
    from services.sim.datagen import episode_length
    from shared.tasks import get_task

    today = {size: episode_length(get_task(task), size) for size in {r["tuples"] for r in records}}
    sizes = {r["tuples"] for r in records if r.get("episode_length") == today[r["tuples"]]}
    return [
        r
        for r in records
        if r["tuples"] not in sizes or r.get("episode_length") == today[r["tuples"]]
    ]


def plot(task: str, records: list[dict[str, Any]], path: Path, looks: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, ax = plt.subplots(figsize=(8, 4.2))
    curves = (  # a colour per measure, a line per model kind
        ("table1_refusals_counted", 0, "o", "C0", "Table I All, refusals counted"),
        ("known_images", None, "s", "C1", "% test images known"),
        ("apn_right", None, "^", "C2", "APN right"),
        ("closed_loop", None, "d", "C3", "closed loop"),
    )
    explored, taught, retrained = kinds(looks)
    for kind, style in (("defaults", "-"), (explored, "--"), (taught, "-."), (retrained, ":")):
        points = [r for r in records if kind in r]
        if points:  # the legend: a line per kind, a colour per measure
            ax.plot([], [], "k" + style, label="recorded, lsr train model" if kind == "defaults"
                    else f"+ {kind}")  # fmt: skip
        for key, index, marker, colour, _ in curves if points else ():
            sizes, means = mean_by_size(points, kind, key, index)
            ax.plot(sizes, means, marker + style, color=colour)
    for _, _, marker, colour, label in curves:
        ax.plot([], [], marker, color=colour, label=label)
    for i, (label, xs, ys) in enumerate(FAMILY.get(task, [])):
        ax.plot(xs, ys, "*", color=f"C{4 + i}", markersize=11, label=label)
    ax.set_xscale("log")
    ax.set_xticks(sorted({r["tuples"] for r in records}))
    ax.xaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel("recorded tuples")
    ax.set_ylabel("%")
    ax.set_ylim(0, 102)
    ax.legend(fontsize=7, loc="lower right")
    ax.set_title(f"{task}: lsr train model with no flags, unseen camera data")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def print_table(records: list[dict[str, Any]], looks: int) -> None:
    """Every model each point measured: as recorded, grown by exploring, trained again."""
    print("tuples seed model               nodes  All(ref) known  apn%  loop%  train_min")
    for r in records:
        for kind in ("defaults", *kinds(looks)):
            if kind not in r:
                continue
            d = r[kind]
            cells = [d["table1_refusals_counted"][0] if d["table1_refusals_counted"] else None,
                     d["known_images"], d["apn_right"], d.get("closed_loop")]  # fmt: skip
            text = " ".join("    -" if v is None else f"{v:5.1f}" for v in cells)
            steps = (
                ("train_model",) if kind == "defaults" else (f"train_model_{kind}", f"train_{kind}")
            )
            wall = next((r["times"][s]["wall"] for s in steps if s in r["times"]), None)
            minutes = "       -" if wall is None else f"{wall / 60:8.1f}"
            print(f"{r['tuples']:6d} {r['seed']:4d} {kind:18s} {d['nodes']:5d} {text} {minutes}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--task", default="box_stacking")
    parser.add_argument("--sizes", type=int, nargs="*", default=[])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="training seeds")
    parser.add_argument("--seed", type=int, default=470000, help="data seeds start here")
    parser.add_argument("--appearance", default="camera")
    parser.add_argument(
        "--episode-length", type=int, help="lsr data generate's (default: its own for the size)"
    )
    parser.add_argument("--test", type=Path, help="unseen test data (default: generated)")
    parser.add_argument("--test-pairs", type=int, default=1000)
    parser.add_argument("--closed-loop", type=int, default=100, help="closed-loop tasks (0: none)")
    parser.add_argument("--loop-seed", type=int, default=47)
    parser.add_argument("--explore", type=int, default=0, help="explored actions (0: none)")
    parser.add_argument(
        "--looks", type=int, default=0, help="lsr explore --looks: no-action pairs per action"
    )
    parser.add_argument(
        "--train-apn",
        action="store_true",
        help="also the explored model with its APN trained again on the explored moves",
    )
    parser.add_argument(
        "--retrain",
        action="store_true",
        help="also train a model again on the recorded and explored tuples (lsr data merge)",
    )
    parser.add_argument("--out", type=Path, default=Path("runs/curves"))
    parser.add_argument("--figure", type=Path)
    parser.add_argument("--kept", type=Path, help="measured points (default: benchmarks/results)")
    args = parser.parse_args()
    args.out = args.out.resolve()
    kept = args.kept or ROOT / "benchmarks" / "results" / f"data_curves_{args.task}.json"
    test = args.test or args.out / "test"
    if args.sizes and not (test / "manifest.json").exists():
        lsr(["data", "generate", "--task", args.task, "--pairs", "1250", "--seed",
             str(args.seed - 1), "--appearance", args.appearance, "--look-pairs", "0",
             "--overwrite", "--out", str(test)], {}, "generate_test")  # fmt: skip
    records = []
    for pairs in args.sizes:
        for seed in args.seeds:
            print(f"{args.task}, {pairs} tuples, training seed {seed}", flush=True)
            records.append(run_point(args, pairs, seed, test))
            keep(kept, records[-1])
            print(json.dumps({k: records[-1][k] for k in ("tuples", "seed", "defaults")}))
    if records:
        (args.out / "RESULTS.json").write_text(json.dumps(records, indent=1) + "\n")
    print_table(records, args.looks)
    if args.figure:
        if not kept.exists():
            sys.exit(f"{kept}: no measured points of {args.task} to draw (run some --sizes)")
        points = recorded_today(args.task, json.loads(kept.read_text()))
        plot(args.task, points, args.figure, args.looks)
        print(f"figure: {args.figure}")


if __name__ == "__main__":
    main()
