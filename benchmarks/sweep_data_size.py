"""Data efficiency: the default pipeline at several training-set sizes, measured end to end.

For each size: `lsr data generate`, `lsr train vae`, `lsr build-roadmap` and `lsr train apn`
with no tuning flags, then Table I on unseen test data (`lsr eval vfm`), the same VAE with
Algorithm 1's roadmap as written (`--eps-rule paper --min-samples 3`) for comparison, and the
APN on the unseen action pairs (`lsr eval apn`) and the closed loop in simulation
(`lsr eval system`). Prints a row per size and writes RESULTS.json
and a figure. The CPU time of each stage is that of its child processes (user + system).

Usage:
  python benchmarks/sweep_data_size.py --task box_stacking --sizes 250 500 1000 2000 5000 \
      --out runs/sweep_box --figure docs/images/data_efficiency_box_stacking.png
Already finished stages are kept (delete a folder to redo it); --seed sets the data seeds.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
LSR = [sys.executable, "-m", "services.cli"]
# The paper's single point: 5000 tuples, VAE-L1 + LSR-L1, 100% All / Any / Trans (Table I).
PAPER_POINT = {"box_stacking": (5000, 100.0)}


def _cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def stage(name: str, args: list[str], done: Path, times: dict[str, Any]) -> str:
    """Run one `lsr` command unless `done` exists; record its wall and CPU seconds."""
    if done.exists():
        return ""
    print(f"  {name}: lsr {' '.join(args)}", flush=True)
    wall, cpu = time.perf_counter(), _cpu()
    result = subprocess.run([*LSR, *args], cwd=ROOT, capture_output=True, text=True)
    if result.returncode:
        sys.exit(f"{name} failed:\n{result.stderr[-3000:]}")
    times[name] = {"wall": time.perf_counter() - wall, "cpu": _cpu() - cpu}
    return result.stdout


def last_json(text: str) -> dict[str, Any]:
    return json.loads(text.strip().splitlines()[-1])


def run_size(args: argparse.Namespace, pairs: int, test: Path) -> dict[str, Any]:
    run = args.out / f"{pairs}"
    model = run / "model"
    record_path = run / "record.json"
    record: dict[str, Any] = (
        json.loads(record_path.read_text()) if record_path.exists() else {"times": {}}
    )
    times = record["times"]
    data = run / "train"
    seed = str(args.seed + pairs)
    stage(
        "generate",
        ["data", "generate", "--task", args.task, "--pairs", str(pairs), "--seed", seed,
         "--size", str(args.size), "--out", str(data)],
        data / "manifest.json",
        times,
    )  # fmt: skip
    stage(
        "vae",
        ["train", "vae", "--data", str(data), "--metric", "l1", "--out", str(model / "vae"),
         "--threads", str(args.threads)],
        model / "vae" / "config.json",
        times,
    )  # fmt: skip
    out = stage(
        "roadmap",
        ["build-roadmap", "--vae", str(model / "vae"), "--data", str(data),
         "--out", str(model / "roadmap")],
        model / "roadmap" / "labels.json",
        times,
    )  # fmt: skip
    if out:
        record["roadmap"] = last_json(out)
    stage(
        "apn",
        ["train", "apn", "--vae", str(model / "vae"), "--data", str(data),
         "--out", str(model / "apn")],
        model / "apn" / "config.json",
        times,
    )  # fmt: skip
    record_path.write_text(json.dumps(record, indent=1))
    evaluate = ["eval", "vfm", "--test", str(test), "--pairs", str(args.test_pairs), "--json"]
    if "table1" not in record:
        out = stage("eval_vfm", [*evaluate, "--model", str(model)], run / "-", times)
        record["table1"] = last_json(out)
        record_path.write_text(json.dumps(record, indent=1))
    if "apn" not in record:
        out = stage("eval_apn", ["eval", "apn", "--model", str(model), "--test", str(test),
                                 "--json"], run / "-", times)  # fmt: skip
        record["apn"] = last_json(out)
        record_path.write_text(json.dumps(record, indent=1))
    paper = run / "paper"
    if "table1_paper_rule" not in record:
        paper.mkdir(exist_ok=True)
        if not (paper / "vae").exists():
            (paper / "vae").symlink_to(Path("..") / "model" / "vae")
        stage(
            "roadmap_paper",
            ["build-roadmap", "--vae", str(model / "vae"), "--data", str(data),
             "--eps-rule", "paper", "--w-eps", "1", "--min-samples", "3",
             "--out", str(paper / "roadmap")],
            paper / "roadmap" / "labels.json",
            times,
        )  # fmt: skip
        out = stage("eval_vfm_paper", [*evaluate, "--model", str(paper)], run / "-", times)
        record["table1_paper_rule"] = last_json(out)
        record_path.write_text(json.dumps(record, indent=1))
    if args.closed_loop and "closed_loop" not in record:
        out = stage("closed_loop", ["eval", "system", "--model", str(model), "--pairs",
                                    str(args.closed_loop), "--json"], run / "-", times)  # fmt: skip
        record["closed_loop"] = last_json(out)
    record_path.write_text(json.dumps(record, indent=1))
    return record


def row(pairs: int, record: dict[str, Any]) -> dict[str, Any]:
    t1, paper = record["table1"], record["table1_paper_rule"]
    loop = record.get("closed_loop", {})
    apn = record.get("apn", {})
    times = record["times"]
    pipeline = ("generate", "vae", "roadmap", "apn")
    return {
        "tuples": pairs,
        "nodes": t1["nodes"],
        "edges": t1["edges"],
        "all": t1["all"],
        "any": t1["any"],
        "trans": t1["trans"],
        "no_path": t1["no_path"],
        # the share of test pairs the training transitions chain together: All's ceiling
        "demonstrated_reach": t1.get("demonstrated_reach"),
        "detour_ratio": t1.get("detour_ratio"),
        "paper_rule_all_any_trans": [paper["all"], paper["any"], paper["trans"]],
        "paper_rule_nodes_edges": [paper["nodes"], paper["edges"]],
        # the same move as the demonstrator's (pixel actions), else pick and release exact
        "apn_right": apn.get("same_move", apn.get("both")),
        "closed_loop_success": loop.get("success"),
        "closed_loop_steps_over_optimal": loop.get("steps_over_optimal"),
        "vae_cpu_minutes": times["vae"]["cpu"] / 60 if "vae" in times else None,
        "pipeline_cpu_minutes": sum(times[s]["cpu"] for s in pipeline if s in times) / 60,
        "pipeline_wall_minutes": sum(times[s]["wall"] for s in pipeline if s in times) / 60,
    }


def plot(task: str, rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = [r["tuples"] for r in rows]
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10, 3.8))
    for key, label, style in (
        ("all", "All", "o-"),
        ("any", "Any", "s--"),
        ("trans", "Trans", "^:"),
    ):
        ax.plot(x, [r[key] for r in rows], style, label=f"% {label} (defaults)")
    if all(r["demonstrated_reach"] is not None for r in rows):
        ax.plot(x, [r["demonstrated_reach"] for r in rows], ":", color="black",
                label="ceiling: pairs the demonstrations connect")  # fmt: skip
    ax.plot(x, [r["paper_rule_all_any_trans"][0] for r in rows], "x-", color="grey",
            label="% All, Algorithm 1 as written")  # fmt: skip
    if any(r["closed_loop_success"] is not None for r in rows):
        ax.plot(x, [r["closed_loop_success"] for r in rows], "d-", label="% closed loop")
    if task in PAPER_POINT:
        ax.plot(*PAPER_POINT[task], "r*", markersize=14, label="paper (Table I)")
    ax.set_xscale("log")
    ax.set_xticks(x, [str(v) for v in x])
    ax.minorticks_off()
    ax.set_xlabel("training tuples")
    ax.set_ylabel("% of unseen start/goal pairs or tasks")
    ax.set_ylim(0, 102)
    ax.legend(fontsize=8, loc="lower right")
    ax.set_title(f"{task}: plans on unseen data")
    ax2.plot(x, [r["nodes"] for r in rows], "o-", label="nodes")
    ax2.plot(x, [r["edges"] for r in rows], "s-", label="edges")
    ax2.set_xscale("log")
    ax2.set_xticks(x, [str(v) for v in x])
    ax2.minorticks_off()
    ax2.set_xlabel("training tuples")
    ax2.legend(fontsize=8)
    ax2.set_title("roadmap size")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--task", default="box_stacking")
    parser.add_argument("--sizes", type=int, nargs="+", default=[250, 500, 1000, 2000, 5000])
    parser.add_argument("--seed", type=int, default=1000, help="data seed = this + size")
    parser.add_argument("--size", type=int, default=64, help="image size")
    parser.add_argument("--test", type=Path, help="test set (default: generated, 1000 tuples)")
    parser.add_argument("--test-pairs", type=int, default=1000)
    parser.add_argument("--closed-loop", type=int, default=200, help="closed-loop tasks (0: none)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads of the VAE run")
    parser.add_argument("--out", type=Path, default=Path("runs/sweep"))
    parser.add_argument("--figure", type=Path)
    args = parser.parse_args()
    args.out = args.out.resolve()
    args.out.mkdir(parents=True, exist_ok=True)
    test = args.test or args.out / "test"
    stage(
        "generate_test",
        ["data", "generate", "--task", args.task, "--pairs", "1000", "--seed", str(args.seed - 1),
         "--size", str(args.size), "--out", str(test)],
        test / "manifest.json",
        {},
    )  # fmt: skip
    rows = []
    for pairs in args.sizes:
        print(f"{args.task}, {pairs} tuples", flush=True)
        rows.append(row(pairs, run_size(args, pairs, test)))
        print(json.dumps(rows[-1]), flush=True)
    (args.out / "RESULTS.json").write_text(json.dumps(rows, indent=1) + "\n")
    header = (
        "tuples nodes edges   All   Any Trans ceiling detour  apn% loop% | paper rule All  cpu_min"
    )
    print(header)
    for r in rows:
        loop, apn, reach = (
            "-" if v is None else f"{v:5.1f}"
            for v in (r["closed_loop_success"], r["apn_right"], r["demonstrated_reach"])
        )
        print(
            f"{r['tuples']:6d} {r['nodes']:5d} {r['edges']:5d} {r['all']:5.1f} {r['any']:5.1f} "
            f"{r['trans']:5.1f} {reach:>7} {r['detour_ratio'] or 0:6.3f} "
            f"{apn} {loop} | {r['paper_rule_all_any_trans'][0]:5.1f}"
            f"  {r['pipeline_cpu_minutes']:6.1f}"
        )
    if args.figure:
        plot(args.task, rows, args.figure)
        print(f"figure: {args.figure}")


if __name__ == "__main__":
    main()
