#!/usr/bin/env bash
# The paper's experiment at 1 M steps (issue 45): the four variants x 3 seeds on the
# paper's training setting (its congestion, `paper-congestion`), train-50 first.
# Resumable: run it again (on any machine, from the committed run state) to go on.
#   PRESET=realistic bash benchmarks/studies/paper-convergence/run.sh   # the realistic drivers
#   MAPS=train-25 VARIANTS=mappo-iadm,diacc ...   # the paper's Table III (25 % map), own folder
#   STUDY=tau ... / STUDY=w_e ...   # the paper's study: diacc, 300k steps x 3 seeds per setting
set -euo pipefail
cd "$(dirname "$0")/../../.."
PRESET=${PRESET:-paper-congestion}
MAPS=${MAPS:-train-50}
JOBS=${JOBS:-2}
OUT="benchmarks/studies/paper-convergence/results/$PRESET"
# Another map than train-50 gets a folder of its own, so its tables never replace
# the committed train-50 ones.
if [ "$MAPS" != train-50 ]; then OUT="$OUT-${MAPS//,/-}"; fi
EXTRA=(--steps 1000000)
if [ -n "${VARIANTS:-}" ]; then EXTRA+=(--variants "$VARIANTS"); fi
if [ -n "${STUDY:-}" ]; then
    OUT="$OUT-study-$STUDY"
    EXTRA=(--steps 300000 --variants diacc --study "$STUDY")
fi
exec diacc reproduce --budget paper "${EXTRA[@]}" --seeds 1,2,3 \
    --style-preset "$PRESET" --maps "$MAPS" --no-transfer \
    --jobs "$JOBS" --set torch_threads=1 --out "$OUT" "$@"
