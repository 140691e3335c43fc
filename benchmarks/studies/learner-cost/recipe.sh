#!/usr/bin/env bash
# Issue 58 item 5: the recipe (today's learner, the `base` arm) over 5 seeds, each at the
# end of its 200k-step schedule, on the `test` stream of the training cell: 30 greedy
# episodes per seed and simulator, 330 steps, and the references (same-mix, the heuristic)
# on the same episodes. Run `ARM=base SEED=S bash run.sh` for S = 1..5 first.
#   bash benchmarks/studies/learner-cost/recipe.sh
#   python benchmarks/studies/learner-cost/recipe.py > benchmarks/studies/learner-cost/results/recipe.md
# Re-running skips finished evaluations (diacc eval resumes).
set -euo pipefail
cd "$(dirname "$0")/../../.."
HERE=benchmarks/studies/learner-cost
SEEDS=${SEEDS:-1 2 3 4 5}
BACKENDS=${BACKENDS:-highway sumo}
export OMP_NUM_THREADS=1
evaluate() {  # policy, output folder
    diacc eval --policy "$1" --backend "$backend" --stream test \
        --grid benchmarks/studies/nopsar-learning/training-cell.toml --episodes 30 \
        --episode-steps 330 --style-preset realistic --out "$2" --no-progress > /dev/null
}
for backend in $BACKENDS; do
    for seed in $SEEDS; do
        evaluate "$HERE/results/base/runs/diacc-s$seed" "$HERE/results/base/eval/test-$backend-200k/diacc-s$seed"
    done
    for ref in same-mix heuristic; do
        evaluate "$ref" "$HERE/results/reference/eval/test-$backend/$ref"
    done
done
