#!/usr/bin/env bash
# Stage the compact run state of every run (about 2.3 MB each; see
# docs/guide/reproducing.md "Across machines") and the finished outputs for a commit.
set -euo pipefail
cd "$(dirname "$0")"
for run in results/*/runs/*/; do
    for f in checkpoint.pt config.json progress.jsonl train.log; do
        [ -f "$run$f" ] && git add -f "$run$f"
    done
done
git add -f results/*/manifest.json 2>/dev/null || true
