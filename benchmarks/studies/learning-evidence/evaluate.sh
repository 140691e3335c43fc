#!/usr/bin/env bash
# Evaluation of the issue-27 runs (benchmarks/studies/learning-evidence/run.sh) on evaluation seeds never
# used in training: the training cell (train-50, N = 25, rho = 0.4, D1), `realistic`, 330-step
# episodes, PSAR horizon `headway` for rules and learners alike, against pure HDV, same-mix,
# the heuristic and cooperative, on both backends (the agents are trained on highway only, so
# SUMO is their transfer check). Finished cells are skipped (resumable).
#
#   RUNS=runs/l27 OUT=runs/l27-eval EPISODES=10 bash benchmarks/studies/learning-evidence/evaluate.sh
#   python benchmarks/studies/learning-evidence/analyse.py runs/l27-eval --out benchmarks/studies/learning-evidence/results
#
# SAMPLED_ON (default highway) lists the backends on which sampled actions are evaluated too;
# GRID another grid file, e.g. benchmarks/grids/zero-shot-geometry.toml (maps never trained on);
# PRESET another HDV style preset, e.g. paper-congestion (the paper's stuck cautious drivers);
# FULL_BRAKE a PSAR full_brake rule for every policy with PSAR (default: each policy's own).
# STREAM the episode seed stream (default validation: these results choose seeds and settings;
# report a chosen agent on `--stream test`, as docs/results/test-stream.md does; results
# committed before 2026-12-04 ran on `legacy`).
set -euo pipefail
runs=${RUNS:-runs/l27}
out=${OUT:-runs/l27-eval}
episodes=${EPISODES:-10}
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
common=(--grid "${GRID:-benchmarks/grids/train-50.toml}" --episodes "$episodes" --style-preset "${PRESET:-realistic}"
        --episode-steps 330 --psar-horizon headway --no-progress --workers "${WORKERS:-1}"
        --stream "${STREAM:-validation}"
        ${FULL_BRAKE:+--psar-full-brake "$FULL_BRAKE"})
for backend in ${BACKENDS:-highway sumo}; do
  for baseline in pure-hdv same-mix heuristic cooperative; do
    nice -n 5 diacc eval --policy "$baseline" --backend "$backend" "${common[@]}" \
      --out "$out/$backend/$baseline" > /dev/null
  done
  for run in "$runs"/*/; do
    [[ -f $run/checkpoint.pt ]] || continue
    # Only finished runs: a run still training has a checkpoint too.
    python - "$run" <<'PY' || { echo "$(basename "$run"): not finished, skipped"; continue; }
import json, sys
run = sys.argv[1]
total = json.load(open(f"{run}/config.json"))["total_steps"]
rows = [json.loads(line) for line in open(f"{run}/progress.jsonl") if line.strip()]
sys.exit(0 if rows and rows[-1]["global_step"] >= total else 1)
PY
    name=$(basename "$run")
    modes=greedy
    [[ " ${SAMPLED_ON:-highway} " == *" $backend "* ]] && modes="greedy sampled"
    for actions in $modes; do
      nice -n 5 diacc eval --policy "$run" --actions "$actions" --backend "$backend" \
        "${common[@]}" --out "$out/$backend/$name-$actions" > /dev/null
    done
  done
  echo "$backend done $(date -u +%H:%M:%S)"
done
