"""How the roadmap depends on w_eps: nodes, edges, purity and Table I figures per value.

Usage: python benchmarks/sweep_w_eps.py --vae models/box_stacking/vae \
           --train data/box_stacking/train --test data/box_stacking/test [--w 0 0.5 1 2 3] \
           [--eps-rule paper|stable]
Choose with a validation set (another seed), not the test set the model is reported on.
"""

from __future__ import annotations

import argparse

from services.encoder.checkpoint import encode_images, load_vae
from services.planner.build import default_metric
from services.planner.evaluate import evaluate_plans, label_nodes, sample_test_pairs
from services.planner.members import encode_pairs, interleave
from services.planner.roadmap import RoadmapConfig, build_roadmap
from shared.dataset import load_dataset
from shared.tasks import get_task


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--vae", required=True)
    parser.add_argument("--train", required=True)
    parser.add_argument("--test", required=True)
    parser.add_argument("--w", type=float, nargs="+", default=[0.0, 0.5, 1.0, 2.0, 3.0])
    parser.add_argument("--min-samples", type=int, default=3)
    parser.add_argument("--pairs", type=int, default=1000)
    parser.add_argument("--eps-rule", default="paper", choices=["paper", "stable"])
    args = parser.parse_args()

    model, config = load_vae(args.vae)
    metric = default_metric(config)
    train = load_dataset(args.train)
    mu1, mu2 = encode_pairs(model, train)
    test = load_dataset(args.test)
    z_test = interleave(encode_images(model, test.image1)[0], encode_images(model, test.image2)[0])
    test_states = interleave(test.state1, test.state2)
    pairs = sample_test_pairs(len(z_test), args.pairs, seed=0)
    point_states = interleave(train.state1, train.state2)
    print(
        f"metric {metric}, min_samples {args.min_samples}, eps rule {args.eps_rule}, "
        f"{args.pairs} test pairs"
    )
    print("w_eps  epsilon  regions  nodes  edges  purity   all    any    trans")
    for w in args.w:
        config = RoadmapConfig(metric, w, args.min_samples, eps_rule=args.eps_rule)
        roadmap = build_roadmap(mu1, mu2, train.a, config)
        labels = label_nodes(
            roadmap.point_node, point_states, roadmap.num_nodes, get_task(train.task)
        )
        r = evaluate_plans(train.task, roadmap, labels, z_test, test_states, pairs, 1000)
        print(
            f"{w:5.1f}  {roadmap.epsilon:7.3f}  {roadmap.stats['regions_before_pruning']:7d}  "
            f"{roadmap.num_nodes:5d}  {len(roadmap.edges):5d}  {labels.purity.mean():6.3f}  "
            f"{r['all']:5.1f}  {r['any']:5.1f}  {r['trans']:6.2f}"
        )


if __name__ == "__main__":
    main()
