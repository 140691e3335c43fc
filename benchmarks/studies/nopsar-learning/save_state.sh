#!/usr/bin/env bash
# Stage the compact state of every run (checkpoint, config, progress, log: ~2.5 MB each;
# what `run.sh` resumes from on another machine) and the evaluation files for a commit.
# Run state is committed at milestones (the end of a stage), not as it goes.
set -euo pipefail
cd "$(dirname "$0")"
for run in results/*/runs/*/; do
    for f in checkpoint.pt config.json progress.jsonl train.log; do
        if [ -f "$run$f" ]; then git add -f "$run$f"; fi
    done
done
for f in results/*/eval/*/*/episodes.csv results/*/eval/*/*/meta.json results/*.md \
    results/*.png results/*.csv; do
    if [ -f "$f" ]; then git add -f "$f"; fi
done
