#!/usr/bin/env bash
# Score the fine-tuned suite agents (finetune.sh) with the scorecard.
#   STREAM=validation: choosing the arm. Every finished run of ARMS x SEEDS and the shipped
#     suite agent (policy-1), suites train + generated (the generator's validation maps),
#     both simulators, 10 episodes per cell, every reference evaluated afresh.
#   STREAM=test: the report, every seed of the chosen arm (ARMS=both), 30 episodes per
#     cell, every suite; the references and the shipped suite agent (folder "suite-s3":
#     suite_means.py --against suite-s3) are copied from its own scorecard
#     (benchmarks/studies/scorecard/results/suite-s3[-sumo], the same test episodes)
#     instead of evaluated again.
#   STREAM=validation bash benchmarks/studies/suite-training/finetune_eval.sh
#   STREAM=test ARMS=both bash benchmarks/studies/suite-training/finetune_eval.sh
# Resumable: finished cells are skipped. A run that has not reached its last step is left out.
set -euo pipefail
cd "$(dirname "$0")/../../.."
HERE=benchmarks/studies/suite-training
STREAM=${STREAM:-validation}
ARMS=${ARMS:-both highway}
SEEDS=${SEEDS:-1 2}
SHIPPED=checkpoints/diacc-suite-mix-realistic-headway-known-s3.pt
OUT="$HERE/results/finetune-card-$STREAM${AT:+-$AT}"
if [ "$STREAM" = validation ]; then
    EPISODES=${EPISODES:-10}; SUITES=${SUITES:-train,generated}; POLICIES=(--policy "$SHIPPED")
else
    EPISODES=${EPISODES:-30}; SUITES=${SUITES:-all}; POLICIES=()
fi
BACKENDS=${BACKENDS:-highway,sumo}
finished() {  # the run's last logged env step is its schedule's last
    python - "$1" <<'PY'
import json, sys
from pathlib import Path
run = Path(sys.argv[1])
steps = json.loads((run / "config.json").read_text())["total_steps"]
last = json.loads((run / "progress.jsonl").read_text().splitlines()[-1])["global_step"]
sys.exit(0 if last >= steps else 1)
PY
}
for seed in $SEEDS; do  # seed-major: a card scored with SEEDS=1 keeps its folders when seed 2 joins
    for arm in $ARMS; do
        run="$HERE/results/finetune-$arm/runs/diacc-s$seed"
        if [ -f "$run/checkpoint.pt" ] && finished "$run"; then
            POLICIES+=(--policy "$run")
        else
            echo "left out (not finished): $run" >&2
        fi
    done
done
if [ "$STREAM" = test ]; then  # references and the shipped suite agent from its own card
    for backend in ${BACKENDS//,/ }; do
        src=benchmarks/studies/scorecard/results/suite-s3
        if [ "$backend" = sumo ]; then src+=-sumo; fi
        for cell in "$src/$backend"/*/; do
            dest="$OUT/$backend/$(basename "$cell")"
            mkdir -p "$dest"
            for ref in same-mix heuristic diacc; do
                [ -d "$dest/$ref" ] || cp -r "$cell/$ref" "$dest/$ref"
            done
            [ -d "$dest/suite-s3" ] || cp -r "$cell/policy" "$dest/suite-s3"
        done
    done
fi
export OMP_NUM_THREADS=1
exec diacc scorecard --stream "$STREAM" --suites "$SUITES" --backends "$BACKENDS" \
    --episodes "$EPISODES" --workers "${WORKERS:-2}" "${POLICIES[@]}" --out "$OUT"
