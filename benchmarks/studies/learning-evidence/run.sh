#!/usr/bin/env bash
# Learning evidence for issue 27: the learning options vs today's defaults (and the
# ablation variants), 3 seeds each, equal steps, on the paper's training cell with
# every driver able to merge (train-50, N = 25, rho = 0.4, D1, `realistic`), highway,
# PSAR horizon `headway` in every run. Resumable: a run with a checkpoint continues
# (--resume), a finished run is skipped. Two runs at a time, one torch thread each.
#
#   OUT=runs/l27 STEPS=200000 JOBS=2 [EXTRA="--set ..."] bash benchmarks/studies/learning-evidence/run.sh [NAME ...]
#
# NAME is SETTING-VARIANT-sSEED, e.g. options-diacc-s1; SETTING is default (the learning
# defaults of 2026-12-02: entropy_coef 0.01), options (every learning option on, with
# entropy 0.01) or lowent (entropy_coef 0.001, the default since 2026-12-03); default: the
# queue below.
# EXTRA: options given to every run of the queue (e.g. "--set env.psar.full_brake=threat").
set -euo pipefail
out=${OUT:-runs/l27}
steps=${STEPS:-200000}
jobs=${JOBS:-2}
extra_all=${EXTRA:-}
export OMP_NUM_THREADS=1 MKL_NUM_THREADS=1
mkdir -p "$out"

options="--set critic_values=per_agent --set env.psar_actions=masked \
 --set env.reward.closeness=bumper --set env.reward.exit_bonus_scale=fleet \
 --set env.reward.delay_weight=1.0 --set env.obs.critic_step_input=false \
 --set env.obs.road_speed_limits=true"

run_one() {
  local name=$1 setting variant seed dir extra
  setting=${name%%-*}
  seed=${name##*-s}
  variant=${name#*-}
  variant=${variant%-s*}
  dir="$out/$name"
  case $setting in
    options) extra="$options --set entropy_coef=0.01" ;;
    default) extra="--set entropy_coef=0.01" ;;  # the paper's entropy bonus, default until 2026-12-03
    lowent) extra="--set entropy_coef=0.001" ;;  # a tenth of it: the default since 2026-12-03
    *) echo "unknown setting '$setting' in '$name' (options, default, lowent)" >&2; return 2 ;;
  esac
  if [[ -f $dir/progress.jsonl ]] && python - "$dir" "$steps" <<'PY'
import json, sys
rows = [json.loads(l) for l in open(sys.argv[1] + "/progress.jsonl") if l.strip()]
sys.exit(0 if rows and rows[-1]["global_step"] >= int(sys.argv[2]) else 1)
PY
  then echo "$name: done"; return 0; fi
  local resume=""
  [[ -f $dir/checkpoint.pt ]] && resume=--resume
  echo "$name: start $(date -u +%H:%M:%S) $resume"
  # shellcheck disable=SC2086
  nice -n 5 diacc train --variant "$variant" --map train-50 --envs 8 --steps "$steps" \
    --seed "$seed" --config configs/small-learner.toml --set env.psar.horizon=headway \
    --set torch_threads=1 --set checkpoint_every=5 $extra $extra_all --no-progress --run-dir "$dir" \
    $resume > "$dir.log" 2>&1 || { echo "$name: FAILED (see $dir.log)"; return 1; }
  echo "$name: end $(date -u +%H:%M:%S)"
}
export -f run_one
export out steps options extra_all

queue=("$@")
if [[ ${#queue[@]} -eq 0 ]]; then
  queue=(options-diacc-s1 default-diacc-s1 options-diacc-s2 default-diacc-s2
         options-diacc-s3 default-diacc-s3 options-mappo-iadm-s1 options-mappo-iadm-s2
         options-mappo-iadm-s3 options-mappo-s1 options-mappo-s2 options-mappo-s3)
fi
printf '%s\n' "${queue[@]}" | xargs -P "$jobs" -I{} bash -c 'run_one {}'
