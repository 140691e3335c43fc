#!/usr/bin/env bash
# Issue 41's measurements on a lent GPU machine (16 cores, one call of < 10 min): the
# learner of the tree at .old/ (the code before the change) against this tree, side by
# side, each process pinned to its own 2 cores; one PPO update on the GPU; and three
# seeds of the shipped recipe with overlap on (2 cores each), stopped by SIGINT at a
# deadline (a checkpoint) if they have not reached 200k steps.
# Prepared here (the image lacks highway-env and its needs; wheels for Python 3.12):
#   git archive 822aaa9 diacc maps configs | (mkdir -p .old && tar -x -C .old)
#   pip download ... -d .whl gymnasium farama-notifications highway-env pettingzoo pygame-ce
#   device run: bash benchmarks/speed/learner_device.sh   (carry .whl and .old)
set -uo pipefail
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
  --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1 MPLBACKEND=Agg
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT" /tmp/runs
LIMIT=${LIMIT:-500}  # seconds for everything but the final copy
{ nproc; uptime; python3 -c "import torch; print(torch.__version__, torch.cuda.is_available())"; } > "$OUT/bench.txt"
B="timeout $LIMIT python3 benchmarks/speed/learner_before_after.py .old ."
$B --what update --rounds 3 --cores 0,1 > /tmp/update.txt 2>&1 &
$B --what train --rounds 2 --cores 2,3 > /tmp/train.txt 2>&1 &
$B --what overlap --rounds 2 --cores 4,5 > /tmp/overlap.txt 2>&1 &
$B --what demand --rounds 1 --updates 2 --demand-envs "${DEMAND_ENVS:-4}" --cores 6,7 > /tmp/demand.txt 2>&1 &
for s in 1 2 3; do
  taskset -c $((8 + 2 * s)),$((9 + 2 * s)) timeout -s INT -k 90 "$LIMIT" python3 -m diacc.cli train \
    --variant diacc --map train-50 --envs 8 --steps 200000 --seed "$s" \
    --config configs/small-learner.toml --set env.psar.horizon=headway --set torch_threads=1 \
    --set checkpoint_every=5 --set overlap=true --no-progress --run-dir "/tmp/runs/overlap-s$s" \
    > "/tmp/runs/overlap-s$s.log" 2>&1 &
done
taskset -c 8,9 timeout "$LIMIT" python3 - > /tmp/gpu.txt 2>&1 <<'PY' &
import time, torch
from diacc.config import PAPER_LEARNER, EnvConfig, TrainConfig, override
from diacc.envs.vector import make_vector_env
from diacc.learn import agent as agent_module, ppo, trainer
torch.set_num_threads(1)
for label, extra in (("small learner", {}), ("paper learner", PAPER_LEARNER)):
    for envs, steps in ((16, 50), (20, 100)):
        cfg = override(TrainConfig(), {"n_envs": envs, "rollout_steps": steps, "device": "cuda",
            "env.map": "train-50", "env.sim.episode_steps": min(steps, EnvConfig().sim.episode_steps), **extra})
        trainer.seed_everything(1)
        dev = torch.device("cuda")
        agent = agent_module.make_agent(cfg, dev)
        vec = make_vector_env(cfg.env, envs, cfg.seed, cfg.vector)
        roll, _, _ = ppo.collect_rollout(agent, vec, cfg, 0, 0, values=False)
        vec.close()
        for bf16 in (False, True):
            c = override(cfg, {"update_bf16": bf16})
            times = []
            for _ in range(4):
                torch.cuda.synchronize(); t0 = time.perf_counter()
                ppo.learn(agent, roll, None, c, dev, vec.n_cavs)
                torch.cuda.synchronize(); times.append(time.perf_counter() - t0)
            best = min(times[1:])
            print(f"{label} {envs}x{steps} bf16={bf16}: values + GAE + PPO update {best:.3f} s "
                  f"(min of 3 after a warm-up): {envs * steps / best:.0f} env-steps/s of learner", flush=True)
PY
wait
for f in update train overlap demand gpu; do echo "== $f"; cat "/tmp/$f.txt"; done >> "$OUT/bench.txt"
for s in 1 2 3; do tail -n 3 "/tmp/runs/overlap-s$s.log"; done >> "$OUT/bench.txt"
tar -C /tmp/runs -cf "$OUT/learning.tar" . 2>/dev/null
cat "$OUT/bench.txt"
