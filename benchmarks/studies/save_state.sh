#!/usr/bin/env bash
# Stage what a new machine needs to go on, and the results, of a study for a commit:
#   bash benchmarks/studies/save_state.sh benchmarks/studies/<study>
# the compact state of every run under <study>/results/*/runs/ (about 2.3 MB each;
# docs/guide/reproducing.md "Across machines"), the merged evaluation files
# (episodes.csv + meta.json; per-cell files and speed samples stay here), tables,
# figures, summaries and the manifest. Run state is committed at milestones.
set -euo pipefail
cd "${1:?name the study folder}"
for run in results/*/runs/*/; do
    for f in checkpoint.pt config.json progress.jsonl train.log; do
        if [ -f "$run$f" ]; then git add -f "$run$f"; fi
    done
done
for f in results/*/eval/*/*/episodes.csv results/*/eval/*/*/meta.json \
    results/*/tables/* results/*/figures/*.png results/*/manifest.json \
    results/*.md results/curves/*; do
    if [ -f "$f" ]; then git add -f "$f"; fi
done
