#!/usr/bin/env bash
# Build the sdist and the wheel (the wheel from the sdist, as an installer would), check
# their metadata, install the wheel into a fresh virtual environment outside the clone and
# run .ci/wheel_smoke.py there. Called by .ci/run after pytest: 2.2 min on 2 quiet cores
# (the fresh environment's install of torch, SUMO and the rest is 80 s of it), 4.5 min
# beside other jobs' disk traffic (writing and deleting its 2 GB, 39,000 files, is slow there).
set -euo pipefail
clone="$(cd "$(dirname "$0")/.." && pwd)"
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
python=${PYTHON:-python}
start=$SECONDS

# pip's output to a log, shown only if it fails.
quiet() { "$@" >"$tmp/step.log" 2>&1 || { cat "$tmp/step.log"; echo "wheel_smoke: failed: $*"; exit 1; }; }

# Build tools in a venv of their own: twine's dependencies stay out of the test environment.
"$python" -m venv "$tmp/tools"
quiet "$tmp/tools/bin/python" -m pip install "build>=1.2,<2" "twine>=6.1,<8"
quiet "$tmp/tools/bin/python" -m build --outdir "$tmp/dist" "$clone"
"$tmp/tools/bin/twine" check --strict "$tmp/dist"/*
wheel=("$tmp/dist"/diacc-*.whl)
sdist=("$tmp/dist"/diacc-*.tar.gz)
# The data and the licence in both: a pattern that misses a file fails here, not for a user.
"$python" - "${wheel[0]}" "${sdist[0]}" <<'PY'
import sys, tarfile, zipfile
wheel, sdist = sys.argv[1:]
want = ("diacc/data/maps/train-25.toml", "diacc/data/checkpoints/diacc-train50-realistic-headway-threat-s1.pt", "LICENSE")
for dist, names in ((wheel, zipfile.ZipFile(wheel).namelist()), (sdist, tarfile.open(sdist).getnames())):
    missing = [w for w in want if not any(n.endswith(w) for n in names)]
    if missing:
        sys.exit(f"wheel_smoke: {dist} lacks {', '.join(missing)}")
PY

# A fresh environment, no site-packages of the machine: every dependency comes from the
# wheel's metadata. The CPU build of torch first, so pip never pulls a CUDA one.
"$python" -m venv "$tmp/venv"
quiet "$tmp/venv/bin/python" -m pip install "torch==2.13.0"
quiet "$tmp/venv/bin/python" -m pip install "${wheel[0]}"
quiet "$tmp/venv/bin/python" -m pip check
echo "wheel_smoke: built, checked and installed $(basename "${wheel[0]}") in $((SECONDS - start)) s"
echo "wheel_smoke: from here $tmp/work, outside the clone"

# From a folder outside the clone, with the venv's commands first on PATH.
mkdir "$tmp/work"
cp "$clone/.ci/wheel_smoke.py" "$tmp/work/"
cd "$tmp/work"
env -u PYTHONPATH PATH="$tmp/venv/bin:$PATH" DIACC_CACHE="$tmp/cache" \
    "$tmp/venv/bin/python" wheel_smoke.py "$clone"
