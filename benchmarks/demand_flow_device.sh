#!/usr/bin/env bash
# Issue 44 items 3-4 on a lent 16-core machine (one call of < 6 min): outflow against
# inflow on the highway backend for humans, the heuristic, the all-round release agent
# and the three demand-fine-tuned agents (benchmarks/results/demand-finetune), every
# policy on the same seeded traffic of the `test` stream: train-50, rho = 0.4, D1,
# `realistic`, 480 s of demand, 120 s warm-up, 480-step episodes, PSAR headway/known.
# The 3600 veh/h cell gets 15 episodes (the fine-tuned agents against their source),
# the others 4. Each job is one `diacc eval` of one policy on one inflow, 16 at once;
# a job still running at the deadline is lost (its cell is not written).
#   device run: bash benchmarks/demand_flow_device.sh   (carry .whl)
set -uo pipefail
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
  --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1 MPLBACKEND=Agg
OUT=${OUT:-/tmp/out}
LIMIT=${LIMIT:-270}  # seconds for every job
mkdir -p "$OUT/flow" /tmp/grids
FT=benchmarks/results/demand-finetune/runs
SOURCE=checkpoints/diacc-train50+train25-3to1-realistic-headway-known-s3.pt
for q in 3600 1600 2400 3200 4000 4800; do
  printf '[[cells]]\nmap = "train-50"\ninflow_vph = %s\ndemand_s = 480\nwarmup_s = 120\ncav_penetration = 0.4\nstyle_mix = "D1"\n' \
    "$q" > "/tmp/grids/q$q.toml"
  n=$([ "$q" = 3600 ] && echo 15 || echo 4)
  echo "release-3to1-s3 $SOURCE $q $n"
  for s in 1 2 3; do echo "demand-ft-s$s $FT/demand-ft-s$s/checkpoint.pt $q $n"; done
  for p in same-mix heuristic pure-hdv; do echo "$p $p $q $n"; done
done > /tmp/jobs.txt
cat > /tmp/job.sh <<'JOB'
label=$1 policy=$2 q=$3 n=$4
python3 -m diacc.cli eval --policy "$policy" --backend highway --grid "/tmp/grids/q$q.toml" \
  --episodes "$n" --episode-steps 480 --stream test --style-preset realistic \
  --psar-horizon headway --psar-full-brake known --no-progress \
  --out "$OUT/flow/$label/q$q" > "/tmp/log-$label-$q.txt" 2>&1
echo "$label $q rc=$? $(date +%s)" >> "$OUT/jobs.txt"
JOB
export OUT
start=$(date +%s)
timeout -k 10 "$LIMIT" xargs -P 16 -L 1 bash /tmp/job.sh < /tmp/jobs.txt
{ nproc; uptime; echo "start $start end $(date +%s)"; tail -n 2 /tmp/log-*.txt; } > "$OUT/device.txt" 2>&1
find "$OUT/flow" -name speeds.csv.gz -delete  # the per-sample speeds are not needed here
