#!/usr/bin/env bash
# APN rows of models/box_stacking/REPORT.md: one APN per VAE trained by benchmarks/table1.sh,
# both output heads for VAE-L1, each evaluated on the unseen test set's action pairs.
# Usage: benchmarks/apn_table.sh [none l1 l2 inf]   (after benchmarks/table1.sh made the VAEs)
set -euo pipefail
cd "$(dirname "$0")/.."
LSR=.venv/bin/lsr
DATA=data/box_stacking
for metric in "$@"; do
  run=runs/vae_$metric
  for head in classify regress; do
    [ "$head" = regress ] && [ "$metric" != l1 ] && continue
    out=$run/apn_$head
    [ -f $out/config.json ] || \
      $LSR train apn --vae $run/vae --data $DATA/train --head $head --epochs 200 --seed 0 --out $out
    $LSR eval apn --model $run --apn $out --test $DATA/test --json | tail -n 1 > $out/eval.json
    cat $out/eval.json
  done
done
