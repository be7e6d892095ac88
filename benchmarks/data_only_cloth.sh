#!/usr/bin/env bash
# The real check of tasks defined by their data (docs/own-data.md, "The real check"): export the
# cloth-folding simulator's dataset as PNG + JSONL (states dropped), import it as a task named
# cloth_recorded with the clean cloth model's settings in its task.json (d_m 13.5, w_eps 0.8,
# regions under 6 pruned), train it with that model's budget (shipped until issue 38, at 975d8f2;
# models/cloth_folding/REPORT.md, "Before issue 38": VAE-L1 30 epochs, lr drop at 20, seed 0; APN
# 200 epochs, seed 0), evaluate it without state labels, then judge its plans in the simulator,
# which it never saw, beside the built-in model (whatever models/cloth_folding now holds).
# Usage: benchmarks/data_only_cloth.sh   (PAIRS=40 by default: the open-loop judge's pairs)
set -euo pipefail
cd "$(dirname "$0")/.."
LSR=.venv/bin/lsr
PY=.venv/bin/python
DATA=data/cloth_folding
RUN=runs/data_only_cloth
PAIRS=${PAIRS:-40}

[ -f $DATA/train/manifest.json ] || $LSR data generate --task cloth_folding --pairs 2000 \
  --seed 0 --size 64 --out $DATA/train
[ -f $DATA/test/manifest.json ] || $LSR data generate --task cloth_folding --pairs 500 \
  --seed 1 --size 64 --out $DATA/test
$LSR data export --data $DATA/train --data $DATA/test --out $RUN/export --overwrite
$PY - $RUN/export/task.json <<'PY'
import json, sys
path = sys.argv[1]
task = json.load(open(path))
task["name"] = "cloth_recorded"
task["settings"] = {"d_m": 13.5, "w_eps": 0.8, "min_samples": 6}
open(path, "w").write(json.dumps(task, indent=2) + "\n")
PY
$LSR data import --from $RUN/export --out $RUN/data --overwrite
[ -f $RUN/model/vae/config.json ] || $LSR train vae --data $RUN/data/train --metric l1 \
  --epochs 30 --lr-drop-epoch 20 --seed 0 --out $RUN/model/vae
$LSR build-roadmap --vae $RUN/model/vae --data $RUN/data/train --eps-rule paper \
  --out $RUN/model/roadmap
$LSR train apn --vae $RUN/model/vae --data $RUN/data/train --epochs 200 --seed 0 \
  --out $RUN/model/apn
$LSR eval vfm --model $RUN/model --test $RUN/data/test --pairs 1000 --seed 0 --json \
  | tail -1 > $RUN/eval_vfm.json
$LSR eval apn --model $RUN/model --test $RUN/data/test --json | tail -1 > $RUN/eval_apn.json
$LSR eval apn --model models/cloth_folding --test $DATA/test --json | tail -1 \
  > $RUN/eval_apn_builtin.json
$PY benchmarks/data_only_judge.py --model $RUN/model --pairs "$PAIRS" | tail -1 \
  > $RUN/judge.json
$PY benchmarks/data_only_judge.py --model models/cloth_folding --pairs "$PAIRS" | tail -1 \
  > $RUN/judge_builtin.json
cat $RUN/eval_vfm.json $RUN/eval_apn.json $RUN/eval_apn_builtin.json $RUN/judge.json \
  $RUN/judge_builtin.json
