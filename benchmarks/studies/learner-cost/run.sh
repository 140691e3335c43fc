#!/usr/bin/env bash
# Issue 58 item 4, learning per CPU-second: today's learner (5 epochs x 4 minibatches)
# against one change at a time, 3 seeds each, on the recipe of the shipped agent (diacc,
# train-50, `realistic`, 8 envs, the 200k-step schedule, one torch thread). Each run stops
# every STAGE steps for a validation evaluation on highway (10 episodes x 330 steps,
# greedy, the training cell), so analyse.py can read the CPU-minutes to a delay.
#   ARM=base SEED=1 bash benchmarks/studies/learner-cost/run.sh
# Resumable: the same command goes on from the committed checkpoint; a stage whose
# evaluation exists is skipped.
set -euo pipefail
cd "$(dirname "$0")/../../.."
ARM=${ARM:?name the arm: base | mb1 | lr1e3 | norm | mb1-norm | mb1-lr2e3 | ent03}
SEED=${SEED:-1}
STAGES=${STAGES:-50000 100000 150000 200000}
case "$ARM" in
    base) SETS=() ;;                             # today's defaults: 5 epochs x 4 minibatches
    mb1) SETS=(--set minibatches=1) ;;           # MAPPO's finding: one minibatch per epoch
    lr1e3) SETS=(--set lr=0.001) ;;              # twice the learning rate: fewer steps to it?
    # Issue 58 item 2: the collapsed actors' GRUs are saturated (logit_probe.py); a
    # LayerNorm on the GRU input, alone and on the arm that collapses every seed
    norm) SETS=(--set model.gru_input_norm=true) ;;
    mb1-norm) SETS=(--set minibatches=1 --set model.gru_input_norm=true) ;;
    # ... or under-stepping: one minibatch moves the policy by a median KL of 2-3e-4 per update;
    # four times the learning rate for a quarter of the gradient steps
    mb1-lr2e3) SETS=(--set minibatches=1 --set lr=0.002) ;;
    # The no-PSAR recipe's entropy bonus (configs/nopsar.toml: 0.01 left one seed in three
    # stalled) on the PSAR recipe, whose default is 0.001: would it do as a library default?
    ent03) SETS=(--set entropy_coef=0.03) ;;
    *) echo "unknown arm: $ARM" >&2; exit 2 ;;
esac
HERE=benchmarks/studies/learner-cost
OUT="$HERE/results/$ARM/runs/diacc-s$SEED"
export OMP_NUM_THREADS=1
reached() {  # the run's last logged env step
    [ -f "$OUT/progress.jsonl" ] || { echo 0; return; }
    tail -n 1 "$OUT/progress.jsonl" | python -c "import json,sys; print(json.loads(sys.stdin.read())['global_step'])"
}
for stop in $STAGES; do
    EVAL="$HERE/results/$ARM/eval/validation-highway-$((stop / 1000))k/diacc-s$SEED"
    [ -f "$EVAL/episodes.csv" ] && continue
    if [ "$(reached)" -lt "$stop" ]; then
        RESUME=()
        if [ -f "$OUT/checkpoint.pt" ]; then RESUME=(--resume); fi
        diacc train --variant diacc --map train-50 --envs 8 --steps 200000 --seed "$SEED" \
            --style-preset realistic --set torch_threads=1 "${SETS[@]}" --stop-at "$stop" \
            --out "$OUT" --no-progress "${RESUME[@]}" > /dev/null
    fi
    diacc eval --policy "$OUT" --backend highway --stream validation \
        --grid benchmarks/studies/nopsar-learning/training-cell.toml --episodes 10 \
        --episode-steps 330 --style-preset realistic --out "$EVAL" --no-progress > /dev/null
done
