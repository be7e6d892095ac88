#!/usr/bin/env bash
# Reproduces models/cloth_folding and the tables of its REPORT.md on this CPU machine: the data,
# VAE-b/L1/L2/Linf, their roadmaps (paper: w_eps 0.8 / 0.2 / -0.3, regions under 6 members
# pruned), Table I (lsr eval vfm), Table II (APNs over 5 seeds, lsr eval apn) and Table III
# (lsr eval system, 200 closed-loop tasks). Usage: benchmarks/cloth_tables.sh [l1 none l2 inf]
# A 30-epoch VAE on 2000 tuples takes about 13 minutes on 2 cores, the closed loop about 15.
# (60 epochs with lr 1e-3 until epoch 40 diverged at epoch 33 for VAE-L1: see the report.)
set -euo pipefail
cd "$(dirname "$0")/.."
LSR=.venv/bin/lsr
DATA=data/cloth_folding
RUNS=runs/cloth
EPOCHS=${EPOCHS:-30}
DROP=${DROP:-20}
PAIRS=${PAIRS:-200}

[ -f $DATA/train/manifest.json ] || $LSR data generate --task cloth_folding --pairs 2000 \
  --seed 0 --size 64 --out $DATA/train
[ -f $DATA/test/manifest.json ] || $LSR data generate --task cloth_folding --pairs 500 \
  --seed 1 --size 64 --out $DATA/test
[ -f $RUNS/state_reader/config.json ] || \
  $LSR train reader --data $DATA/train --test $DATA/test --out $RUNS/state_reader

metrics=("$@")
[ ${#metrics[@]} -gt 0 ] || metrics=(l1 none l2 inf)
for metric in "${metrics[@]}"; do
  run=$RUNS/vae_$metric
  # As for box stacking: L2 and Linf apply the action term to the encoder means.
  case $metric in l2) w=0.2 on=mean ;; inf) w=-0.3 on=mean ;; *) w=0.8 on=sample ;; esac
  [ -f $run/vae/config.json ] || \
    $LSR train vae --data $DATA/train --metric $metric --epochs $EPOCHS --lr-drop-epoch $DROP \
      --action-on $on --seed 0 --out $run/vae
  $LSR build-roadmap --vae $run/vae --data $DATA/train --w-eps $w --min-samples 6 \
    --eps-rule paper --out $run/roadmap | tail -n 1 > $run/roadmap.json
  $LSR eval vfm --model $run --test $DATA/test --pairs 1000 --seed 0 \
    --reader $RUNS/state_reader --figure $run/class_distances.png --json | tail -n 1 \
    > $run/table1.json
  for seed in 0 1 2 3 4; do
    [ -f $run/apn_s$seed/config.json ] || \
      $LSR train apn --vae $run/vae --data $DATA/train --epochs 200 --seed $seed \
        --out $run/apn_s$seed
    $LSR eval apn --model $run --apn $run/apn_s$seed --test $DATA/test --json | tail -n 1 \
      > $run/apn_s$seed/eval.json
  done
  rm -rf $run/apn && cp -r $run/apn_s0 $run/apn
  $LSR eval system --model $run --pairs $PAIRS --seed 0 --json | tail -n 1 > $run/table3.json
  cat $run/table1.json $run/table3.json
done
