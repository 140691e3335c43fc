#!/usr/bin/env bash
# Smoke comparison of the learning options (docs/concepts/learning-options.md): today's
# defaults vs every option on, same seeds and steps. A smoke test that the
# options train end to end, NOT evidence for adopting any of them (issue 27
# asks for 3 seeds x up to 1 M steps for that).
#
#   bash benchmarks/studies/learning-options-smoke/run.sh [STEPS] [SEEDS...]
set -euo pipefail
steps=${1:-6000}
shift || true
seeds=${*:-1 2}
out=${OUT:-runs/learning-options-smoke}
options=(
  --set critic_values=per_agent
  --set env.psar_actions=masked
  --set env.reward.closeness=bumper
  --set env.reward.exit_bonus_scale=fleet
  --set env.reward.delay_weight=1.0
  --set env.obs.critic_step_input=false
  --set env.obs.road_speed_limits=true
)
for seed in $seeds; do
  common=(--variant diacc --map train-50 --envs 4 --steps "$steps" --seed "$seed"
          --config configs/small-learner.toml --no-progress)
  diacc train "${common[@]}" --run-dir "$out/default-s$seed" > /dev/null
  diacc train "${common[@]}" "${options[@]}" --run-dir "$out/options-s$seed" > /dev/null
done
python benchmarks/studies/learning-options-smoke/analyse.py "$out" $seeds
