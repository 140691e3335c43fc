#!/usr/bin/env bash
# Issue 60 item 2: agents trained across the suite. DIACC (PSAR on) on the training mix
# of configs/suite-train.toml (shipped and 40 generated training maps, N 15-40, CAV share
# 0.1-0.8, D1-D3, realistic + paper-congestion drivers, release + demand with every CAV
# an agent), highway, 20 envs, a 1 M-step schedule, 3 seeds; checkpoints and settings
# are chosen on `validation` only (diacc eval --stream validation; the generated
# validation maps), the scorecard on `test` reports every seed.
#   SEED=1 STOP=200000 bash benchmarks/studies/suite-training/run.sh
# Resumable: the same command goes on from the committed checkpoint (--resume).
set -euo pipefail
cd "$(dirname "$0")/../../.."
SEED=${SEED:-1}
STOP=${STOP:-1000000}
OUT="benchmarks/studies/suite-training/results/mix/runs/diacc-s$SEED"
RESUME=()
if [ -f "$OUT/checkpoint.pt" ]; then RESUME=(--resume); fi
export OMP_NUM_THREADS=1
exec diacc train --variant diacc --config configs/suite-train.toml --steps 1000000 --envs 20 \
    --seed "$SEED" --set torch_threads=1 --stop-at "$STOP" --out "$OUT" --no-progress \
    "${RESUME[@]}"
