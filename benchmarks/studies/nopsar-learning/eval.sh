#!/usr/bin/env bash
# Evaluate every run of an arm on the training cell: greedy, 330-step episodes, wrecks
# removed (evaluation's rule), both simulators. validation chooses; test reports.
#   ARM=remove STREAM=validation bash benchmarks/studies/nopsar-learning/eval.sh
# The baseline (the paper-convergence study's 1 M-step `end` runs, trained longer):
#   ARM=end-1M RUNS=benchmarks/studies/paper-convergence/results/realistic/runs \
#       PATTERN='diacc-nopsar-*' bash benchmarks/studies/nopsar-learning/eval.sh
# The references on the same episodes (same-mix, the heuristic under PSAR, pure HDV):
#   ARM=reference bash benchmarks/studies/nopsar-learning/eval.sh
# Re-running skips finished cells (diacc eval resumes); AT=600k names a later checkpoint's
# folder (eval/validation-highway-600k/...), so it does not skip the earlier one's.
# GRID=FILE plays other cells, e.g. the paper's dense zero-shot rows (issue 60 item 4):
#   ARM=own-penalty50-ent03-sumo-brake4 STREAM=test EPISODES=30 AT=dense \
#       GRID=benchmarks/studies/paper-convergence/dense-rows.toml bash .../eval.sh
set -euo pipefail
cd "$(dirname "$0")/../../.."
ARM=${ARM:?name the arm}
STREAM=${STREAM:-validation}
EPISODES=${EPISODES:-10}
BACKENDS=${BACKENDS:-highway sumo}
HERE=benchmarks/studies/nopsar-learning
RUNS=${RUNS:-$HERE/results/$ARM/runs}
PATTERN=${PATTERN:-*}
GRID=${GRID:-$HERE/training-cell.toml}
export OMP_NUM_THREADS=1
if [ "$ARM" = reference ]; then POLICIES=(same-mix heuristic pure-hdv); else POLICIES=("$RUNS"/$PATTERN/); fi
for run in "${POLICIES[@]}"; do
    name=$(basename "$run")
    for backend in $BACKENDS; do
        diacc eval --policy "$run" --backend "$backend" --stream "$STREAM" \
            --grid "$GRID" --episodes "$EPISODES" --episode-steps 330 \
            --style-preset realistic --out "$HERE/results/$ARM/eval/$STREAM-$backend${AT:+-$AT}/$name" \
            --no-progress
    done
done
