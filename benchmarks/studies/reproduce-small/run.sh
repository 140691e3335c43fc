#!/usr/bin/env bash
# The committed `diacc reproduce` result (docs/results/reproduce-small.md): all four variants on train-25 and train-50, seeds 1-3, 50k env steps
# each (4 envs, the small learner of configs/small-learner.toml), diacc also trained
# on SUMO for the transfer, evaluated with the paper-congestion preset and 330-step
# episodes on both backends, 4 episodes per cell, 4 zero-shot cells per test map;
# once with greedy and once with sampled actions (same checkpoints), then the small
# files (tables, PNG figures, transfer report, manifests, per-episode rows, training
# progress) copied to DEST.
#
#   bash benchmarks/studies/reproduce-small/run.sh WORK DEST
#
# WORK holds the full runs (checkpoints, speeds); run it again to continue after
# an interruption (finished runs and cells are skipped).
set -euo pipefail
work=$1
dest=$2
common=(--budget small --steps 50000 --seeds "${SEEDS:-1,2,3}" --envs 4 --episodes 4 --zero-shot-cells 4
  --style-preset paper-congestion --episode-steps 330 --jobs "${JOBS:-2}" --no-progress
  --set minibatches=4 --set model.hidden_dim=64 --set model.gru_hidden=64)
diacc reproduce "${common[@]}" --out "$work/greedy"
mkdir -p "$work/sampled"
cp -rn "$work/greedy/runs" "$work/sampled/"  # the same checkpoints: nothing is retrained
diacc reproduce "${common[@]}" --actions sampled --out "$work/sampled"

for actions in greedy sampled; do
  src=$work/$actions
  out=$dest/$actions
  mkdir -p "$out/figures" "$out/tables"
  cp "$src"/tables/*.md "$src"/tables/*.tex "$out/tables/"
  cp "$src"/figures/*.png "$out/figures/"
  cp "$src"/transfer.md "$src"/transfer.csv "$src"/manifest.json "$out/"
  for dir in "$src"/eval/*/*/; do
    rel=${dir#"$src"/}
    mkdir -p "$out/$rel"
    cp "$dir/episodes.csv" "$dir/meta.json" "$out/$rel"
  done
done
mkdir -p "$dest/progress"
for run in "$work"/greedy/runs/*/; do
  gzip -c "$run/progress.jsonl" > "$dest/progress/$(basename "$run").jsonl.gz"
done
