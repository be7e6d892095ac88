#!/usr/bin/env bash
# Reproduces models/<task> of a folding task and the tables of its REPORT.md on this CPU machine:
# the data, VAE-b/L1/L2/Linf, their roadmaps (paper: w_eps 0.8 / 0.2 / -0.3, regions under 6
# members pruned), Table I (lsr eval vfm), Table II (APNs over 5 seeds, lsr eval apn) and
# Table III (lsr eval system, closed-loop tasks).
# Usage: [TASK=tshirt_folding] benchmarks/folding_tables.sh [l1 none l2 inf]
# TASK defaults to cloth_folding (2000 training tuples, runs/cloth); tshirt_folding takes the
# paper's 1283 tuples under its default camera appearance and is also evaluated on `shifted`
# test data. Cloth: a 30-epoch VAE on 2000 tuples takes about 13 minutes on 2 cores.
# (60 epochs with lr 1e-3 until epoch 40 diverged at epoch 33 for cloth VAE-L1: see its report.)
set -euo pipefail
cd "$(dirname "$0")/.."
LSR=.venv/bin/lsr
TASK=${TASK:-cloth_folding}
DATA=data/$TASK
# cloth: 30 epochs, lr drop at 20 (its shipped schedule); others: the trainer's default steps
case $TASK in
  cloth_folding) RUNS=${RUNS:-runs/cloth} TUPLES=${TUPLES:-2000} \
    LENGTH=${LENGTH:---epochs 30 --lr-drop-epoch 20} ;;
  *) RUNS=${RUNS:-runs/$TASK} TUPLES=${TUPLES:-1283} LENGTH=${LENGTH:-} ;;
esac
PAIRS=${PAIRS:-200}
# cloth keeps its clean renders; the T-shirt is also tested on doubled appearance ranges
SHIFTED=$([ "$TASK" = cloth_folding ] && echo "" || echo test_shifted)

[ -f $DATA/train/manifest.json ] || $LSR data generate --task $TASK --pairs $TUPLES \
  --seed 0 --size 64 --out $DATA/train
[ -f $DATA/test/manifest.json ] || $LSR data generate --task $TASK --pairs 500 \
  --seed 1 --size 64 --out $DATA/test
if [ -n "$SHIFTED" ] && [ ! -f $DATA/test_shifted/manifest.json ]; then
  $LSR data generate --task $TASK --pairs 500 --seed 2 --size 64 --appearance shifted \
    --out $DATA/test_shifted
fi
[ -f $RUNS/state_reader/config.json ] || \
  $LSR train reader --data $DATA/train --test $DATA/test --out $RUNS/state_reader

metrics=("$@")
[ ${#metrics[@]} -gt 0 ] || metrics=(l1 none l2 inf)
for metric in "${metrics[@]}"; do
  run=$RUNS/vae_$metric
  # As for box stacking: L2 and Linf apply the action term to the encoder means.
  case $metric in l2) w=0.2 on=mean ;; inf) w=-0.3 on=mean ;; *) w=0.8 on=sample ;; esac
  [ -f $run/vae/config.json ] || \
    $LSR train vae --data $DATA/train --metric $metric $LENGTH --action-on $on --seed 0 \
      --out $run/vae
  $LSR build-roadmap --vae $run/vae --data $DATA/train --w-eps $w --min-samples 6 \
    --eps-rule paper --out $run/roadmap | tail -n 1 > $run/roadmap.json
  for test in test $SHIFTED; do
    suffix=${test#test}  # "" or _shifted (test_shifted)
    $LSR eval vfm --model $run --test $DATA/$test --pairs 1000 --seed 0 \
      --reader $RUNS/state_reader --figure $run/class_distances$suffix.png --json | tail -n 1 \
      > $run/table1$suffix.json
  done
  for seed in 0 1 2 3 4; do
    [ -f $run/apn_s$seed/config.json ] || \
      $LSR train apn --vae $run/vae --data $DATA/train --epochs 200 --seed $seed \
        --out $run/apn_s$seed
    for test in test $SHIFTED; do
      suffix=${test#test}
      $LSR eval apn --model $run --apn $run/apn_s$seed --test $DATA/$test --json | tail -n 1 \
        > $run/apn_s$seed/eval$suffix.json
    done
  done
  rm -rf $run/apn && cp -r $run/apn_s0 $run/apn
  $LSR eval system --model $run --pairs $PAIRS --seed 0 --json | tail -n 1 > $run/table3.json
  if [ -n "$SHIFTED" ]; then
    $LSR eval system --model $run --pairs $PAIRS --seed 0 --appearance shifted --json \
      | tail -n 1 > $run/table3_shifted.json
  fi
  cat $run/table1.json $run/table3.json
done
