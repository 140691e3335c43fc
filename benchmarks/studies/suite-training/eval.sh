#!/usr/bin/env bash
# Score the suite-trained seeds with the scorecard: STREAM=validation (the default) to
# choose a seed and compare recipes, STREAM=test to report (every seed, never the best).
#   bash benchmarks/studies/suite-training/eval.sh                       # validation
#   STREAM=test EPISODES=30 SUITES=all BACKENDS=highway,sumo bash .../eval.sh
# Every seed's run directory that holds a checkpoint is scored (in seed order, so a
# resumed card keeps its policy-1, policy-2 ... folders); finished cells are skipped.
# SEEDS="1 2" scores those seeds only (a seed still training joins the card later).
set -euo pipefail
cd "$(dirname "$0")/../../.."
HERE=benchmarks/studies/suite-training
STREAM=${STREAM:-validation}
EPISODES=${EPISODES:-10}
SUITES=${SUITES:-train,generated,demand,zero-shot}
BACKENDS=${BACKENDS:-highway}
WORKERS=${WORKERS:-2}
POLICIES=()
for run in "$HERE"/results/mix/runs/diacc-s*/; do
    seed=$(basename "$run"); seed=${seed#diacc-s}
    if [ -n "${SEEDS:-}" ] && [[ " $SEEDS " != *" $seed "* ]]; then continue; fi
    if [ -f "$run/checkpoint.pt" ]; then POLICIES+=(--policy "$run"); fi
done
export OMP_NUM_THREADS=1
exec diacc scorecard --stream "$STREAM" --suites "$SUITES" --backends "$BACKENDS" \
    --episodes "$EPISODES" --workers "$WORKERS" "${POLICIES[@]}" \
    --out "$HERE/results/mix/card-$STREAM${AT:+-$AT}"
