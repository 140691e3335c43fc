#!/usr/bin/env bash
# The paper's headline cells with the paper's stuck drivers (issue 45 item 4): the training
# cells of the paper's tables (`--grid train`: train-25 and train-50, N = 25, rho = 0.4, D1),
# HDV preset `paper-congestion`, 330-step episodes, PSAR horizon `headway` with full_brake
# `known`; pure HDV, same-mix, cooperative and the shipped agent (greedy) on both backends,
# episodes of the `test` stream. Finished cells are skipped.
#
#   OUT=runs/paper-vs-ours EPISODES=10 bash benchmarks/studies/paper-vs-ours/run.sh
#   diacc table runs/paper-vs-ours/highway/* --rows speed,p_we,p_sce,collision,delay
#
# GRID=zero-shot plays the paper's zero-shot rows (test-25 and test-50) instead.
set -euo pipefail
out=${OUT:-runs/paper-vs-ours}
episodes=${EPISODES:-10}
agent=${AGENT:-checkpoints/diacc-train50-realistic-headway-threat-s1.pt}
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
common=(--grid "${GRID:-train}" --episodes "$episodes" --style-preset "${PRESET:-paper-congestion}"
        --episode-steps 330 --psar-horizon headway --psar-full-brake known --no-progress
        --stream "${STREAM:-test}" --workers "${WORKERS:-1}")
for backend in ${BACKENDS:-highway sumo}; do
  for baseline in pure-hdv same-mix cooperative; do
    nice -n 10 diacc eval --policy "$baseline" --backend "$backend" "${common[@]}" \
      --out "$out/$backend/$baseline" > /dev/null
  done
  nice -n 10 diacc eval --policy "$agent" --actions greedy --backend "$backend" \
    "${common[@]}" --out "$out/$backend/diacc-greedy" > /dev/null
  echo "$backend done $(date -u +%H:%M:%S)"
done
