#!/usr/bin/env bash
# The committed "trained agent vs human traffic" result (docs/results/trained-agent.md):
# evaluate DIACC checkpoints trained on highway (train-50, paper-congestion),
# each with sampled and greedy actions, and the non-learning baselines (pure HDV,
# same-mix: the CAV slots driven by normal human drivers, cooperative, and the
# scripted heuristic under PSAR) on the paper's training cells, on both
# backends, with 330-step episodes, then write the tables with the flow rows.
#
#   PRESET=paper-congestion EPISODES=10 bash benchmarks/studies/trained-agent/run.sh OUT RUN_DIR...
#
# PRESET (default paper-congestion) is the HDV style preset, BACKENDS (default
# "highway sumo") the backends. Finished cells are skipped, so an interrupted
# run continues where it stopped.
set -euo pipefail
out=$1; shift
episodes=${EPISODES:-10}
preset=${PRESET:-paper-congestion}
common=(--grid train --episodes "$episodes" --style-preset "$preset" --episode-steps 330 --no-progress --workers "${WORKERS:-2}")
for backend in ${BACKENDS:-highway sumo}; do
  for baseline in pure-hdv same-mix cooperative heuristic; do
    diacc eval --policy "$baseline" --backend "$backend" "${common[@]}" --out "$out/$backend/$baseline"
  done
  for run in "$@"; do
    for actions in sampled greedy; do
      diacc eval --policy "$run" --actions "$actions" --backend "$backend" "${common[@]}" \
        --out "$out/$backend/$(basename "$run" .pt)-$actions"
    done
  done
  diacc table "$out/$backend"/* --rows speed,p_we,p_sce,collision,arrived,flow --out "$out/table-$backend.md"
done
