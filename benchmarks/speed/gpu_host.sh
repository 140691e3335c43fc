#!/usr/bin/env bash
# Issue 63's measurements on a lent GPU host, in one device call of < 8 minutes:
#  1. benchmarks/speed/gpu_update.py: one PPO update (16 envs x 50 steps, the default
#     small learner) on the CPU, eager on the GPU, static on the GPU, static compiled
#     (CUDA graphs), with each path's losses and weights against the CPU's and the host
#     syncs inside the static epochs;
#  2. diacc bench --training --only device: end to end (rollout + update) env-steps/s and
#     learner s / update, the CPU path beside the GPU paths and the env workers (one
#     process per core), 3 updates each (the first not timed), without and then with
#     the compiled row (compiling takes its first update).
# Everything goes to $OUT (update.txt, training.txt, training-compiled.txt, host.txt).
#
# Prepared here first (the image lacks highway-env and what diacc needs of it): in the
# repo root, with the versions this repo's CI uses (pip list here),
#   echo /.whl/ >> .git/info/exclude
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 \
#     --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
#     --platform manylinux2014_x86_64 -d .whl gymnasium==1.4.0 farama-notifications==0.0.6 \
#     highway-env==1.12.1 pettingzoo==1.27.0 pygame-ce==2.5.8
# then the device call (carry .whl; timeout_s 540):
#   bash benchmarks/speed/gpu_host.sh
# Dry run on a machine without a GPU (every path on the CPU; minutes):
#   DEVICE=cpu ENVS=4 STEPS=20 bash benchmarks/speed/gpu_host.sh
set -uo pipefail
if compgen -G ".whl/*.whl" > /dev/null; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site:$PWD
else
  export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
fi
export PYTHONUNBUFFERED=1 MPLBACKEND=Agg
OUT=${OUT:-/tmp/gpu-host-out}
DEVICE=${DEVICE:-cuda} ENVS=${ENVS:-16} STEPS=${STEPS:-50}
mkdir -p "$OUT"
{
  date -u; nproc; uptime
  python3 -c "import torch; print(torch.__version__, torch.cuda.is_available())"
  command -v nvidia-smi > /dev/null && nvidia-smi -L
  git log --oneline -1 2>/dev/null
} > "$OUT/host.txt" 2>&1
cat "$OUT/host.txt"
echo "== one update"
NO_COMPILE=$([ "$DEVICE" = cuda ] || echo --no-compile)  # inductor on a CPU takes minutes
timeout 170 python3 benchmarks/speed/gpu_update.py --device "$DEVICE" --envs "$ENVS" \
  --rollout-steps "$STEPS" --repeats 5 $NO_COMPILE 2>&1 | tee "$OUT/update.txt"
echo "== end to end (bench --training --only device, no compile)"
timeout 130 python3 -m diacc.experiments.bench.training --device "$DEVICE" --only device \
  --envs "$ENVS" --rollout-steps "$STEPS" --updates 3 --no-compile 2>&1 | tee "$OUT/training.txt"
if [ "$DEVICE" = cuda ]; then
  echo "== end to end, compiled static update (its first update compiles, not timed)"
  timeout 150 python3 -m diacc.experiments.bench.training --device cuda --only device \
    --envs "$ENVS" --rollout-steps "$STEPS" --updates 3 \
    --rows "small learner on cuda: compiled static update + env workers" \
    2>&1 | tee "$OUT/training-compiled.txt"
fi
