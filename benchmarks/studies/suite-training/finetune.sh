#!/usr/bin/env bash
# Issue 60: the shipped suite agent (seed 3) fine-tuned on the training mix for STEPS more
# env steps, one change at a time against the same fine-tuning on highway alone:
#   ARM=both     mix.backends = highway, sumo (each block's simulator in turn)
#   ARM=highway  the mix as trained (highway only): the control, equal steps
# The shipped agent never saw SUMO and is level with the rule there (its scorecard,
# docs/results/suite-training.md); does SUMO in the mix close that gap?
#   ARM=both SEED=1 bash benchmarks/studies/suite-training/finetune.sh
# Resumable: the same command goes on from the committed checkpoint (--resume).
set -euo pipefail
cd "$(dirname "$0")/../../.."
ARM=${ARM:?name the arm: both | highway}
SEED=${SEED:-1}
STEPS=${STEPS:-200000}
case "$ARM" in
    both) SETS=(--set mix.backends=highway,sumo) ;;
    highway) SETS=() ;;
    *) echo "unknown arm: $ARM (both | highway)" >&2; exit 2 ;;
esac
OUT="benchmarks/studies/suite-training/results/finetune-$ARM/runs/diacc-s$SEED"
START=(--init-from checkpoints/diacc-suite-mix-realistic-headway-known-s3.pt)
if [ -f "$OUT/checkpoint.pt" ]; then START=(--resume); fi
export OMP_NUM_THREADS=1
exec diacc train --variant diacc --config configs/suite-train.toml --steps "$STEPS" --envs 20 \
    --seed "$SEED" --set torch_threads=1 "${SETS[@]}" --stop-at "${STOP:-$STEPS}" --out "$OUT" \
    --no-progress "${START[@]}"
