#!/usr/bin/env bash
# README's main comparison on the `test` seed stream (issue 42): the training cell (train-50,
# N = 25, rho = 0.4, D1), `realistic`, 330-step episodes, PSAR horizon `headway` and
# full_brake `known` for every policy with PSAR; pure HDV, same-mix, cooperative, the heuristic
# and the shipped agent (greedy and sampled) on both backends. Finished cells are skipped.
#
#   OUT=runs/test-stream EPISODES=30 bash benchmarks/studies/test-stream/run.sh
#   diacc table runs/test-stream/highway/* --rows delay,throughput,p_sce,collision
#
# The episodes are the `test` stream's: the agent was chosen (among six seeds) on `legacy`
# episodes, which no test episode repeats.
set -euo pipefail
out=${OUT:-runs/test-stream}
episodes=${EPISODES:-30}
agent=${AGENT:-checkpoints/diacc-train50-realistic-headway-threat-s1.pt}
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
common=(--grid benchmarks/grids/train-50.toml --episodes "$episodes" --style-preset realistic
        --episode-steps 330 --psar-horizon headway --psar-full-brake known --no-progress
        --stream "${STREAM:-test}" --workers "${WORKERS:-1}")
for backend in ${BACKENDS:-highway sumo}; do
  for baseline in pure-hdv same-mix cooperative heuristic; do
    nice -n 10 diacc eval --policy "$baseline" --backend "$backend" "${common[@]}" \
      --out "$out/$backend/$baseline" > /dev/null
  done
  for actions in greedy sampled; do
    nice -n 10 diacc eval --policy "$agent" --actions "$actions" --backend "$backend" \
      "${common[@]}" --out "$out/$backend/diacc-$actions" > /dev/null
  done
  echo "$backend done $(date -u +%H:%M:%S)"
done
