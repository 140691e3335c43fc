#!/usr/bin/env bash
# Issue 44 item 3 on a lent GPU machine (16 cores, one call of < 10 min): three seeds of
# the all-round release agent fine-tuned on the demand scenario (3600 veh/h into
# train-50, 40 % CAVs, 600-step episodes), each run with 4 env worker processes and its
# PPO update on the GPU (a CPU update if CUDA fails to start), stopped by SIGINT at a
# deadline (checkpoint saved; `diacc train --resume` continues on any machine).
# Prepared here (the image lacks highway-env and its needs; wheels for Python 3.12):
#   pip download ... -d .whl gymnasium farama-notifications highway-env pettingzoo pygame-ce
#   device run: bash benchmarks/studies/demand-training/finetune_device.sh   (carry .whl)
set -uo pipefail
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
  --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1 MPLBACKEND=Agg
OUT=${OUT:-/tmp/out}
LIMIT=${LIMIT:-460}  # seconds of training; the rest of the call packs the results
SOURCE=checkpoints/diacc-train50+train25-3to1-realistic-headway-known-s3.pt
mkdir -p "$OUT" /tmp/runs
{ nproc; uptime; python3 -c "import torch; print(torch.__version__, torch.cuda.is_available())"; } > "$OUT/device.txt"
run() {  # seed device deadline_s
  taskset -c "$4" timeout -s INT -k 60 "$3" python3 -m diacc.cli train --variant diacc \
    --map train-50 --envs 4 --steps 96000 --seed "$1" --device "$2" \
    --config configs/small-learner.toml --set env.psar.horizon=headway \
    --set env.psar.full_brake=known --set torch_threads=1 --set entropy_coef=0.001 \
    --set env.scenario.kind=demand --set env.scenario.inflow_vph=3600 \
    --set env.scenario.demand_s=480 --set env.scenario.warmup_s=120 --set env.scenario.cav_slots=16 \
    --set env.obs.max_vehicles=320 --set env.sim.episode_steps=600 --set rollout_steps=600 \
    --set minibatches=24 --set vector=process --set checkpoint_every=1 \
    --init-from "$SOURCE" --no-progress --out "/tmp/runs/demand-ft-s$1" \
    >> "/tmp/runs/demand-ft-s$1.log" 2>&1
}
start=$(date +%s)
for s in 1 2 3; do
  cores="$((5 * s - 5))-$((5 * s - 1))"
  (
    run "$s" cuda "$LIMIT" "$cores"
    used=$(( $(date +%s) - start ))
    if [ ! -f "/tmp/runs/demand-ft-s$s/checkpoint.pt" ] && [ "$used" -lt 120 ]; then
      echo "== CUDA run failed after ${used} s: CPU update instead" >> "/tmp/runs/demand-ft-s$s.log"
      rm -rf "/tmp/runs/demand-ft-s$s"
      run "$s" cpu "$((LIMIT - used))" "$cores"
    fi
  ) &
done
wait
for s in 1 2 3; do echo "== seed $s"; tail -n 4 "/tmp/runs/demand-ft-s$s.log"; done >> "$OUT/device.txt"
tar -C /tmp/runs -czf "$OUT/demand-ft.tgz" .
ls -la "$OUT" >> "$OUT/device.txt"
