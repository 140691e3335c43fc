#!/usr/bin/env bash
# The committed "trained agent vs human traffic" result (README "Trained agent"):
# evaluate DIACC checkpoints trained on highway (train-50, paper-congestion) and
# the two non-learning baselines on the paper's training cells, on both
# backends, with the paper-congestion preset and 330-step episodes (README
# "Congestion presets"), then write the tables.
#
#   bash benchmarks/trained_vs_hdv.sh OUT RUN_DIR...
#
# Finished cells are skipped, so an interrupted run continues where it stopped.
set -euo pipefail
out=$1; shift
episodes=${EPISODES:-10}
common=(--grid train --episodes "$episodes" --style-preset paper-congestion --episode-steps 330 --no-progress --workers "${WORKERS:-2}")
for backend in highway sumo; do
  for baseline in pure-hdv cooperative; do
    diacc eval --policy "$baseline" --backend "$backend" "${common[@]}" --out "$out/$backend/$baseline"
  done
  for run in "$@"; do
    for actions in sampled greedy; do
      diacc eval --policy "$run" --actions "$actions" --backend "$backend" "${common[@]}" \
        --out "$out/$backend/$(basename "$run" .pt)-$actions"
    done
  done
  diacc table "$out/$backend"/* --rows speed,p_we,p_sce,collision,arrived --out "$out/table-$backend.md"
done
