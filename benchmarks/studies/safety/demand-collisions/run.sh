#!/usr/bin/env bash
# Issue 57: collisions on the demand road, before and after the fixes. Every PSAR policy
# (the heuristic, the release agent) on both simulators and same-mix on highway (its own
# human drivers), at 1600-4800 veh/h, 10 `test` episodes per point, every CAV an agent:
# the protocol of benchmarks/studies/demand-training/flow.sh (SLOTS=every), whose
# committed results are the "before". Results: $OUT/flow-every-cav/<backend>/<policy>/q<inflow>/
#   OUT=runs/demand-collisions bash benchmarks/studies/safety/demand-collisions/run.sh
#   then: python benchmarks/studies/safety/demand-collisions/count.py runs/demand-collisions
set -uo pipefail
export OUT=${OUT:-runs/demand-collisions} SLOTS=every EPISODES=${EPISODES:-10}
export EPISODES_3600=$EPISODES INFLOWS=${INFLOWS:-1600 2400 3200 3600 4000 4800}
here=$(dirname "$0")
BACKEND=sumo LABELS="heuristic release-3to1-s3" bash "$here/../../demand-training/flow.sh"
BACKEND=highway LABELS="same-mix heuristic release-3to1-s3" bash "$here/../../demand-training/flow.sh"
