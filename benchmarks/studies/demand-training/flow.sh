#!/usr/bin/env bash
# Issue 44 items 3-4: outflow against inflow, one `diacc eval` per (policy, inflow), for
# humans, the heuristic, the all-round release agent and the three demand-fine-tuned
# agents (benchmarks/studies/demand-training/results/finetune), every policy on the same seeded traffic of
# the `test` stream: train-50, rho = 0.4, D1, `realistic`, 480 s of demand, 120 s
# warm-up, 480-step episodes, PSAR headway/known. Results: $OUT/flow/<backend>/<label>/q<inflow>/
# (diacc eval's directories; `diacc table` and `diacc plot flow` read them), packed into
# $OUT/flow.tgz at the end (a lent machine returns only shallow folders).
#   BACKEND=highway PARALLEL=16 LIMIT=270 EPISODES=4 EPISODES_3600=15 bash benchmarks/studies/demand-training/flow.sh
#   (on a lent machine without highway-env: WHEELS=.whl installs it from wheels first)
#   SLOTS=every: every CAV gets an agent slot (`diacc eval --agent-slots every`); results
#   then go to $OUT/flow-every-cav/<backend>/ (default SLOTS=own: the policy's 16 slots)
#   RHO=0.1: another CAV share (default 0.4); results then go to $OUT/flow[-every-cav]-rho0.1/
set -uo pipefail
if [ -n "${WHEELS:-}" ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site "$WHEELS"/*.whl || exit 1
  export PYTHONPATH=/tmp/site:$PWD
fi
export PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1 MPLBACKEND=Agg
export OUT=${OUT:-/tmp/out} BACKEND=${BACKEND:-highway} SLOTS=${SLOTS:-own}
export RHO=${RHO:-0.4}
# One root per protocol (diacc plot flow draws a root's policies per backend).
export ROOT=flow$([ "$SLOTS" = every ] && echo -every-cav)$([ "$RHO" = 0.4 ] || echo "-rho$RHO")
LIMIT=${LIMIT:-100000}  # seconds for every job; a job still running then is lost
INFLOWS=${INFLOWS:-3600 1600 2400 3200 4000 4800}
LABELS=${LABELS:-release-3to1-s3 demand-ft-s1 demand-ft-s2 demand-ft-s3 same-mix heuristic pure-hdv}
GRIDS=$(mktemp -d)
declare -A POLICY=(
  [release-3to1-s3]=checkpoints/diacc-train50+train25-3to1-realistic-headway-known-s3.pt
  [demand-ft-s1]=benchmarks/studies/demand-training/results/finetune/seed-1/checkpoint.pt
  [demand-ft-s2]=benchmarks/studies/demand-training/results/finetune/seed-2/checkpoint.pt
  [demand-ft-s3]=benchmarks/studies/demand-training/results/finetune/seed-3/checkpoint.pt
  # issue 60's agents trained across the suite (demands with every CAV an agent among them)
  [suite-s1]=benchmarks/studies/suite-training/results/mix/runs/diacc-s1/checkpoint.pt
  [suite-s2]=benchmarks/studies/suite-training/results/mix/runs/diacc-s2/checkpoint.pt
  [suite-s3]=benchmarks/studies/suite-training/results/mix/runs/diacc-s3/checkpoint.pt
)
mkdir -p "$OUT/$ROOT"
for q in $INFLOWS; do
  printf '[[cells]]\nmap = "train-50"\ninflow_vph = %s\ndemand_s = 480\nwarmup_s = 120\ncav_penetration = %s\nstyle_mix = "D1"\n' \
    "$q" "$RHO" > "$GRIDS/q$q.toml"
  n=$([ "$q" = 3600 ] && echo "${EPISODES_3600:-15}" || echo "${EPISODES:-4}")
  for label in $LABELS; do echo "$label ${POLICY[$label]:-$label} $GRIDS/q$q.toml $q $n"; done
done > "$GRIDS/jobs.txt"
cat > "$GRIDS/job.sh" <<'JOB'
label=$1 policy=$2 grid=$3 q=$4 n=$5
python3 -m diacc.cli eval --policy "$policy" --backend "$BACKEND" --grid "$grid" \
  --episodes "$n" --episode-steps 480 --stream test --style-preset realistic \
  --psar-horizon headway --psar-full-brake known --agent-slots "$SLOTS" --no-progress \
  --out "$OUT/$ROOT/$BACKEND/$label/q$q" > "$OUT/$ROOT/log-$BACKEND-$label-$q.txt" 2>&1
echo "$ROOT $BACKEND $label $q rc=$? $(date +%s)" >> "$OUT/$ROOT/jobs.txt"
JOB
timeout -k 10 "$LIMIT" xargs -P "${PARALLEL:-2}" -L 1 bash "$GRIDS/job.sh" < "$GRIDS/jobs.txt"
find "$OUT/$ROOT" -name speeds.csv.gz -delete  # per-sample speeds are not needed here
tar -C "$OUT" -czf "$OUT/$ROOT.tgz" "$ROOT"
