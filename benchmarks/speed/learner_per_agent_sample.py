"""The learner's cost per agent-sample: the one-shot release against the demand scenario.

Issue 41 item 5 asks the demand scenario's PPO update to cost within 1.5x of the
release's per *agent-sample* (one CAV decision the update learns from), with its
memory bounded and stated. One process per case (fresh memory high-water mark),
alternating, one thread: a seeded rollout (``values=False``), then one full
``learn`` (critic values, GAE, PPO epochs) timed in CPU seconds of the thread;
agent-samples are the rollout's decisions of alive CAVs; peak resident memory
is the process's high-water mark after the update::

    OMP_NUM_THREADS=1 python benchmarks/speed/learner_per_agent_sample.py --rounds 2
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

CASES = {
    # the default learner on the paper's training cell (16 envs x 100 steps)
    "release": {"n_envs": 16, "rollout_steps": 100, "env.map": "train-50"},
    # benchmarks/demand_training_speed.py's setting: 3600 veh/h, 4 envs x 600 steps
    "demand": {
        "n_envs": 4, "rollout_steps": 600, "env.map": "train-50", "minibatches": 24,
        "env.sim.episode_steps": 600, "env.obs.max_vehicles": 320,
        "env.scenario.kind": "demand", "env.scenario.inflow_vph": 3600.0,
        "env.scenario.demand_s": 480.0, "env.scenario.warmup_s": 120.0,
        "env.scenario.cav_slots": 16,  # the measured setting (the default until "every")
    },
}  # fmt: skip

CHILD = """
import json, resource, sys, time, torch
from diacc.config import TrainConfig, override
from diacc.envs.vector import make_vector_env
from diacc.learn import ppo
from diacc.learn.agent import make_agent
from diacc.learn.trainer import seed_everything
from diacc.threads import set_torch_threads
set_torch_threads(1)
cfg = override(TrainConfig(), {"device": "cpu", **json.loads(sys.argv[1])})
seed_everything(1)
agent = make_agent(cfg, torch.device("cpu"))
vec = make_vector_env(cfg.env, cfg.n_envs, cfg.seed, cfg.vector)
roll, _, stats = ppo.collect_rollout(agent, vec, cfg, 0, 0, values=False)
vec.close()
t0 = time.thread_time()
ppo.learn(agent, roll, None, cfg, torch.device("cpu"), vec.n_cavs)
cpu_s = time.thread_time() - t0
peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps({"cpu_s": cpu_s, "samples": stats.decisions, "peak_mib": peak_mib}))
"""


def run(case: str) -> dict:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    out = subprocess.run(
        [sys.executable, "-c", CHILD, json.dumps(CASES[case])],
        env=env, capture_output=True, text=True, check=False,
    )  # fmt: skip
    if out.returncode:
        last = out.stderr.strip().splitlines()[-1]
        sys.exit(f"learner_per_agent_sample: {case} failed: {last}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=2)
    args = parser.parse_args()
    print(f"# load average {os.getloadavg()}")
    costs: dict[str, list[float]] = {case: [] for case in CASES}
    for r in range(args.rounds):
        for case in CASES:
            result = run(case)
            per_k = 1000 * result["cpu_s"] / result["samples"]
            costs[case].append(per_k)
            print(
                f"round {r + 1} {case:8s} update {result['cpu_s']:6.2f} CPU s, "
                f"{result['samples']:6d} agent-samples, {per_k:.3f} CPU s per 1000, "
                f"peak {result['peak_mib']:.0f} MiB", flush=True,
            )  # fmt: skip
    median = {case: sorted(v)[len(v) // 2] for case, v in costs.items()}
    print(f"# demand / release per agent-sample: x{median['demand'] / median['release']:.2f}")
    print(f"# load average {os.getloadavg()}")


if __name__ == "__main__":
    main()
