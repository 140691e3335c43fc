#!/usr/bin/env bash
# The demand targets of issues 58 and 60 for the suite-trained seeds: outflow at
# 4800 veh/h into train-50 with every CAV driven by the agent, against same-mix and the
# all-round release agent on the same `test` traffic (480 s of demand, 120 s warm-up,
# 480-step episodes, D1, realistic, PSAR headway/known), through the demand study's
# flow.sh. RHO=0.4 (issue 58: >= +25 % against same-mix) or RHO=0.1 (issue 60: >= +10 %).
#   BACKEND=highway RHO=0.4 SEEDS="1 2 3" bash benchmarks/studies/suite-training/demand.sh
# Results: results/mix/demand/flow-every-cav[-rho0.1]/<backend>/<label>/q4800/ (diacc
# eval's folders: `diacc table` reads them); a finished (policy, backend) is skipped.
set -euo pipefail
cd "$(dirname "$0")/../../.."
LABELS=${REFS-same-mix release-3to1-s3}  # REFS="" once the references are done
for seed in ${SEEDS:-1 2 3}; do LABELS="$LABELS suite-s$seed"; done
export OUT=benchmarks/studies/suite-training/results/mix/demand SLOTS=every INFLOWS=4800
export EPISODES=${EPISODES:-10} LABELS PARALLEL=${PARALLEL:-1}
bash benchmarks/studies/demand-training/flow.sh
rm -f "$OUT"/*.tgz  # flow.sh packs its folders for lent machines; here they are the results
