#!/usr/bin/env bash
# The scorecard's full output for the shipped agent (issue 42): every suite (train, zero-shot,
# geometry, paper-congestion, demand), both backends, 30 episodes per cell of the `test` seed
# stream, against same-mix and the heuristic (the agent is the reference itself, so its
# "vs DIACC" column is empty). Resumable: finished cells are skipped.
#
#   bash benchmarks/studies/scorecard/run.sh            # ~1.5 CPU hours (2 workers: ~50 min)
#   POLICY=checkpoints/diacc-suite-mix-realistic-headway-known-s3.pt \
#     OUT=benchmarks/studies/scorecard/results/suite-s3 SUITES=all BACKENDS=highway bash .../run.sh
#
# Run from the repository root (the geometry maps and the agent live there).
set -euo pipefail
out=${OUT:-benchmarks/studies/scorecard/results/shipped-threat-s1}
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
nice -n 10 diacc scorecard \
  --policy "${POLICY:-checkpoints/diacc-train50-realistic-headway-threat-s1.pt}" \
  --suites "${SUITES:-train,zero-shot,geometry,paper-congestion,demand}" \
  --episodes "${EPISODES:-30}" --backends "${BACKENDS:-highway,sumo}" \
  --workers "${WORKERS:-2}" --out "$out"
