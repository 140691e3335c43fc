#!/usr/bin/env bash
# The separate check of examples/rllib_ppo.py (RLlib pins gymnasium 1.2.2, so CI's
# environment cannot hold it): install this clone with its rllib extra, under
# examples/rllib-constraints.txt, into a fresh virtual environment, and run the example at
# its tiny budget there. About 4 min on 2 cores. Usage: bash examples/rllib_check.sh
set -euo pipefail
clone="$(cd "$(dirname "$0")/.." && pwd)"
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
"${PYTHON:-python}" -m venv "$tmp/venv"
# pip's output to a log, shown only if it fails.
quiet() { "$@" >"$tmp/step.log" 2>&1 || { cat "$tmp/step.log"; echo "rllib check: failed: $*"; exit 1; }; }
pip=("$tmp/venv/bin/python" -m pip install -c "$clone/examples/rllib-constraints.txt")
# torch first, by itself: pip then never pulls a CUDA build.
quiet "${pip[@]}" torch
quiet "${pip[@]}" "$clone[rllib]"
quiet "$tmp/venv/bin/python" -m pip check
"$tmp/venv/bin/python" -c 'import gymnasium, ray; print("rllib check: ray", ray.__version__, "gymnasium", gymnasium.__version__)'
cd "$tmp"  # diacc from the environment, not from the clone
env -u PYTHONPATH "$tmp/venv/bin/python" "$clone/examples/rllib_ppo.py" --iterations 1 | tee "$tmp/out.txt"
grep -q "^iteration 1: " "$tmp/out.txt"
echo "rllib check: 1 passed, 0 failed"
