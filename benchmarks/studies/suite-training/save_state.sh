#!/usr/bin/env bash
# Stage this study's run state and results for a commit (benchmarks/studies/save_state.sh).
exec bash "$(dirname "$0")/../save_state.sh" "$(dirname "$0")"
