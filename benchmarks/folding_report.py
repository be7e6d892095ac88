"""Markdown tables for a folding task's REPORT.md from what benchmarks/folding_tables.sh wrote.

Usage: python benchmarks/folding_report.py [runs/cloth]. Prints Table I (VFM), Table II (APN,
mean and standard deviation over the seeds) and Table III (closed loop) for every VAE found,
beside the paper's figures (its Tables II and III are its T-shirt study), once per test
appearance found: the test data's own and, where evaluated, `shifted` (files ending _shifted).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

NAMES = {"none": "b", "l1": "L1", "l2": "L2", "inf": "Linf"}
PAPER_TABLE2 = {  # paper Table II: pick, release, total (mean +- std over 5 seeds)
    "none": ("2.12 ± 0.34", "2.21 ± 0.13", "4.47 ± 0.39"),
    "l1": ("1.86 ± 0.11", "2.03 ± 0.07", "3.96 ± 0.16"),
    "l2": ("2.06 ± 0.14", "2.05 ± 0.07", "4.22 ± 0.2"),
    "inf": ("1.98 ± 0.13", "2.16 ± 0.1", "4.3 ± 0.16"),
}
PAPER_TABLE3 = {"l1": (80, 90, 100, 100), "l2": (40, 77, 60, 60), "inf": (24, 44, 56, 36)}


def read(path: Path) -> dict | None:
    """A JSON result, or None while it is missing or still being written."""
    text = path.read_text().strip() if path.is_file() else ""
    return json.loads(text) if text else None


def main(root: Path) -> None:
    runs = [(m, root / f"vae_{m}") for m in NAMES if (root / f"vae_{m}").is_dir()]
    for suffix in ("", "_shifted"):
        if suffix == "" or any((run / f"table1{suffix}.json").is_file() for _, run in runs):
            print(f"## Test data: {'shifted appearance' if suffix else 'as trained'}\n")
            tables(runs, suffix)


def tables(runs: list[tuple[str, Path]], suffix: str) -> None:
    print("Table I: 1000 start/goal pairs of unseen test images\n")
    print("| model | nodes / edges | purity | All | Any | Trans | decoded read as claimed "
          "| classes separated | min inter - max intra |")  # fmt: skip
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for metric, run in runs:
        t = read(run / f"table1{suffix}.json")
        if t:
            print(
                f"| VAE-{NAMES[metric]} | {t['nodes']} / {t['edges']} | "
                f"{t['node_purity_mean']:.3f} | {t['all']:.1f} | {t['any']:.1f} | "
                f"{t['trans']:.1f} | {t.get('decoded_agreement', float('nan')):.1f} | "
                f"{t.get('classes_separated')} / {t.get('classes')} | "
                f"{t.get('mean_min_inter_minus_max_intra', float('nan')):+.2f} |"
            )
    shown = [(metric, read(run / f"table1{suffix}.json")) for metric, run in runs]
    shown = [(metric, t["shown_pairs"]) for metric, t in shown if t and "shown_pairs" in t]
    if shown:
        print("\nThe same pairs whose two ends show every part of their state (`Task.hidden`)\n")
        print("| model | pairs | All | Any | Trans |\n| --- | --- | --- | --- | --- |")
        for metric, s in shown:
            print(f"| VAE-{NAMES[metric]} | {s['pairs']} | {s['all']:.1f} | {s['any']:.1f} | "
                  f"{s['trans']:.1f} |")  # fmt: skip
    print("\nTable II: APN error on the unseen test action pairs, 5 seeds (paper beside)\n")
    print("| model | pick | release | total | clicks' own noise (total) | paper pick / release / "
          "total | pick px (mean) | release px (mean) | same move |")  # fmt: skip
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for metric, run in runs:
        evals = [read(p) for p in sorted(run.glob(f"apn_s*/eval{suffix}.json"))]
        evals = [e for e in evals if e]
        if not evals:
            continue

        def stat(get, evals=evals, digits=4) -> str:
            values = np.array([get(e) for e in evals])
            return f"{values.mean():.{digits}f} ± {values.std():.{digits}f}"

        paper = " / ".join(PAPER_TABLE2[metric])
        print(
            f"| APN-{NAMES[metric]} ({len(evals)} seeds) | {stat(lambda e: e['mse']['pick'])} | "
            f"{stat(lambda e: e['mse']['release'])} | {stat(lambda e: e['mse']['total'])} | "
            f"{stat(lambda e: e['mse_click_noise']['total'])} | {paper} | "
            f"{stat(lambda e: e['pick_pixels']['mean'], digits=2)} | "
            f"{stat(lambda e: e['release_pixels']['mean'], digits=2)} | "
            f"{stat(lambda e: e['same_move'], digits=1)} |"
        )
    print("\nTable III: closed loop in simulation, re-planning after every action (paper beside)\n")
    print("| framework | tasks | system | transitions (as seen) | VFM | APN "
          "| paper (5 goals x 5 runs) |")  # fmt: skip
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for metric, run in runs:
        t = read(run / f"table3{suffix}.json")
        if t and "table3" in t:
            r = t["table3"]
            paper = " / ".join(str(v) for v in PAPER_TABLE3.get(metric, ())) or "-"
            seen = r.get("transitions_as_seen")  # results before it was measured lack it
            seen = f" ({seen:.1f})" if seen is not None else ""
            print(
                f"| F-{NAMES[metric]} | {t['pairs']} | {r['system']:.1f} | "
                f"{r['transitions']:.1f}{seen} | {r['vfm']:.1f} | {r['apn']:.1f} | {paper} |"
            )
    print()


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("runs/cloth"))
