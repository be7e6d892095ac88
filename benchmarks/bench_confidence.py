"""How often plans at a confidence are valid (issue 21): a reliability table from held-out data.

Usage:
    .venv/bin/python benchmarks/bench_confidence.py --model models/box_stacking \
        --test data/box_stacking/test [--pairs 1000] [--seed 0] [--max-plans 8]

Plans between seeded start/goal pairs of unseen test images, as `/plan` makes them (refusal on:
pairs with an unknown end get no plan and are counted apart). A plan is valid when its first
node shows the start image's true state, its last the goal's, and every APN action, applied by
the task's rules to one node's state, gives the next node's. Two plan figures are in every plan
reply: `confidence`, the product of the APN's confidences, and `support`, the product over steps
of (w + 1) / (w + 2) for a step backed by w training pairs. Prints markdown: for each figure the
plans and valid share per band, then for each cut the share of plans at or above it and how
many of those were valid; then validity by plan length, and the area under the ROC curve of
each figure (0.5: says nothing of validity; 1: separates valid plans from the rest).
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from services.planner.action_plans import ActionPlanner
from services.planner.build import load_labels
from services.planner.eval_vfm import load_test_images
from services.planner.evaluate import TransitionChecker, sample_test_pairs
from services.planner.versions import roadmap_dir
from shared.plans import UnknownImageError

BANDS = (0.0, 0.1, 0.2, 0.3, 0.5, 0.7, 0.9, 1.0 + 1e-9)
CUTS = (0.1, 0.2, 0.3, 0.5, 0.7, 0.9)


def auc(score: np.ndarray, valid: np.ndarray) -> float:
    """The chance that a valid plan scores above an invalid one (ties count half)."""
    good, bad = score[valid], score[~valid]
    if not len(good) or not len(bad):
        return float("nan")
    above = (good[:, None] > bad[None, :]).mean() + 0.5 * (good[:, None] == bad[None, :]).mean()
    return float(above)


def reliability(name: str, c: np.ndarray, v: np.ndarray) -> None:
    """Markdown: plans and valid share per band of a figure, then per cut."""
    print(f"\n| plan {name} | plans | valid |\n| --- | --- | --- |")
    for low, high in itertools.pairwise(BANDS):
        band = (c >= low) & (c < high)
        shown = f"{low:g} - {min(high, 1.0):g}"
        rate = f"{100 * v[band].mean():.1f}%" if band.any() else "-"
        print(f"| {shown} | {int(band.sum())} | {rate} |")
    print(f"\n| {name} cut: plans at or above | share of plans | of those valid | valid below |")
    print("| --- | --- | --- | --- |")
    for cut in CUTS:
        kept = c >= cut
        above = f"{100 * v[kept].mean():.1f}%" if kept.any() else "-"
        below = f"{100 * v[~kept].mean():.1f}%" if (~kept).any() else "-"
        print(f"| {cut:g} | {100 * kept.mean():.1f}% | {above} | {below} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, required=True)
    parser.add_argument("--test", type=Path, required=True)
    parser.add_argument("--pairs", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-plans", type=int, default=8)
    args = parser.parse_args()

    planner = ActionPlanner.from_model_dir(args.model)
    task = planner.task
    labels = load_labels(roadmap_dir(args.model), task.name)
    node_states = [task.array_to_state(s) for s in labels.states]
    checker = TransitionChecker(task)  # judged by views, as plans are
    images, states, _ = load_test_images(args.test)
    z, errors = planner.planner.look(images)
    confidence, support, steps, valid = [], [], [], []
    refused = no_plan = 0
    for i, j in tqdm(sample_test_pairs(len(images), args.pairs, args.seed), desc="pairs"):
        start, goal = task.array_to_state(states[i]), task.array_to_state(states[j])
        try:
            plans = planner.plan_latent(z[i], z[j], args.max_plans, errors[[i, j]])
        except UnknownImageError:
            refused += 1
            continue
        no_plan += not plans
        for plan in plans:
            path = [node_states[n] for n in plan.nodes]
            ok = checker.same(path[0], start) and checker.same(path[-1], goal)
            ok = ok and checker.actions_lead(path, plan.actions)
            confidence.append(plan.confidence)
            support.append(plan.support)
            steps.append(len(plan.actions))
            valid.append(ok)
    v = np.array(valid, bool)
    print(f"{args.model} on {args.test}: {args.pairs} pairs (seed {args.seed}), {len(v)} plans, "
          f"{refused} pairs refused, {no_plan} without a path; {100 * v.mean():.1f}% of plans "
          "valid")  # fmt: skip
    figures = {"support": np.array(support), "confidence": np.array(confidence)}
    for name, c in figures.items():
        reliability(name, c, v)
    n = np.array(steps)
    print("\n| actions | plans | valid |\n| --- | --- | --- |")
    for k in np.unique(n):
        print(f"| {k} | {int((n == k).sum())} | {100 * v[n == k].mean():.1f}% |")
    shown = ", ".join(f"{name} {auc(c, v):.3f}" for name, c in figures.items())
    print(f"\nROC AUC: {shown}, fewer actions {auc(-n.astype(float), v):.3f}")


if __name__ == "__main__":
    main()
