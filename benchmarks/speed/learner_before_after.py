"""The learner of two source trees side by side in one run (issue 41's targets).

Each measurement runs in a fresh process per tree, the trees alternating for
``--rounds`` rounds so that both see the same machine load:

* ``update``: CPU seconds of one PPO update of the default learner on the
  same seeded rollout (``--envs`` envs x ``--rollout-steps`` steps, highway,
  ``train-50``), one torch thread; the median of ``--repeats`` updates;
* ``train``: env-steps/s of ``diacc train`` end to end (the default config on
  ``train-50``, ``--envs`` envs, 100-step rollouts, ``--updates`` updates, the
  first left out), synchronous;
* ``overlap``: the same with ``overlap = true`` (the rollout beside the update);
* ``demand``: ``train`` on the demand scenario (3600 veh/h into ``train-50``,
  600-step episodes, ``--demand-envs`` envs, critic rows for 320 vehicles on
  the road, 24 minibatches: ``benchmarks/speed/demand_training_speed.py``'s setting).

``--cores`` pins every process to those CPUs (``taskset``), so that a run on a
larger machine measures the 2-core case::

    git worktree add /tmp/before 822aaa9
    python benchmarks/speed/learner_before_after.py /tmp/before . --what update train overlap

Prints one row per round and tree, and the ratio of the medians (new over old).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

SNIPPET = r"""
import json, sys, time
import torch
from diacc.config import EnvConfig, TrainConfig, override
try:  # the learner split into ppo / buffer / agent (issue 43)
    from diacc.learn import agent as agent_module, buffer, ppo
    from diacc.envs.vector import make_vector_env
    from diacc.learn.trainer import seed_everything
    learner = ppo
except ImportError:  # one module before it
    from diacc.learn import mappo as learner
    agent_module = buffer = learner
    make_vector_env, seed_everything = learner.make_vector_env, learner.seed_everything
from diacc.threads import set_torch_threads
what, envs, steps, updates, repeats, demand_envs = sys.argv[1], *map(int, sys.argv[2:7])
if what == "update":
    cfg = override(TrainConfig(), {"n_envs": envs, "rollout_steps": steps, "device": "cpu",
        "env.map": "train-50", "env.sim.episode_steps": min(steps, EnvConfig().sim.episode_steps)})
    seed_everything(1)
    set_torch_threads(1)
    agent = agent_module.make_agent(cfg, torch.device("cpu"))
    vec = make_vector_env(cfg.env, envs, cfg.seed, cfg.vector)
    # The rollout's 5th argument: the training step (after issue 43), tau (before); both
    # give tau_init here.
    start = 0 if learner.__name__.endswith(".ppo") else cfg.env.reward.tau_init
    roll, next_value, _ = learner.collect_rollout(agent, vec, cfg, 0, start)
    vec.close()
    adv, ret = learner.rollout_gae(roll, next_value, cfg)
    batch = buffer.make_batch(roll, adv, ret, cfg.chunk_len, torch.device("cpu"))
    import resource
    seconds, faults, system = [], [], []
    for _ in range(repeats + 1):
        r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.thread_time()
        learner.ppo_update(agent, batch, cfg, vec.n_cavs)
        r1 = resource.getrusage(resource.RUSAGE_SELF)
        seconds.append(time.thread_time() - t0)
        faults.append(r1.ru_minflt - r0.ru_minflt)
        system.append(r1.ru_stime - r0.ru_stime)
    mid = lambda v: sorted(v[1:])[repeats // 2]
    print(json.dumps({"value": mid(seconds), "unit": "CPU s / update",
                      "minor_faults": mid(faults), "system_cpu_s": mid(system)}))
else:
    from diacc.experiments.bench.training import measure
    options = {"env.map": "train-50", "overlap": what == "overlap"}
    n = envs
    rollout_steps = 100
    if what == "demand":
        from diacc.sim.scenario import Scenario
        scenario = Scenario(kind="demand", inflow_vph=3600, demand_s=480, warmup_s=120,
                            cav_penetration=0.4, cav_slots=16)  # the default until "every"
        options.update({"env.scenario": scenario, "env.obs.max_vehicles": 320,
                        "minibatches": 24, "env.sim.episode_steps": 600})
        n, rollout_steps = demand_envs, 600
    result = measure("diacc", "highway", n, updates, "cpu", rollout_steps, "auto", options)
    print(json.dumps({"value": result["steps_per_s"], "unit": "env-steps/s",
                      "learner_cpu_s": result["learner_cpu_s"],
                      "rollout_cpu_s": result["rollout_cpu_s"]}))
"""


def run(tree: Path, what: str, args: argparse.Namespace) -> dict:
    path = os.pathsep.join(filter(None, [str(tree.resolve()), os.environ.get("PYTHONPATH")]))
    env = {**os.environ, "PYTHONPATH": path, "OMP_NUM_THREADS": "1"}
    cmd = [sys.executable, "-c", SNIPPET, what, str(args.envs), str(args.rollout_steps)]
    cmd += [str(args.updates), str(args.repeats), str(args.demand_envs)]
    if args.cores:
        cmd = ["taskset", "-c", args.cores, *cmd]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    if out.returncode:
        tail = (out.stderr.strip().splitlines() or ["no output"])[-1]
        sys.exit(f"learner_before_after: {what} failed in {tree}: {tail}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("old", type=Path)
    p.add_argument("new", type=Path)
    p.add_argument(
        "--what",
        nargs="+",
        default=["update", "train", "overlap"],
        choices=("update", "train", "overlap", "demand"),
    )
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--envs", type=int, default=16)
    p.add_argument("--rollout-steps", type=int, default=50, help="of the update's rollout")
    p.add_argument("--updates", type=int, default=4, help="of each training (first not timed)")
    p.add_argument("--repeats", type=int, default=3, help="timed updates per update round")
    p.add_argument("--demand-envs", type=int, default=8)
    p.add_argument("--cores", default="", help="taskset CPU list, e.g. 0,1")
    args = p.parse_args(argv)
    for tree in (args.old, args.new):
        if not (tree / "diacc" / "__init__.py").is_file():
            sys.exit(f"learner_before_after: {tree} holds no diacc source tree")
    print(f"# load average {os.getloadavg()}; cores {args.cores or 'any'}", flush=True)
    for what in args.what:
        values: dict[str, list[float]] = {"old": [], "new": []}
        for r in range(args.rounds):
            for name, tree in (("old", args.old), ("new", args.new)):
                result = run(tree, what, args)
                values[name].append(result["value"])
                extra = {k: round(v, 3) for k, v in result.items() if k not in ("value", "unit")}
                print(
                    f"{what:8s} round {r + 1} {name}: {result['value']:.3f} {result['unit']}"
                    f" {extra or ''}",
                    flush=True,
                )
        old, new = statistics.median(values["old"]), statistics.median(values["new"])
        ratio = old / new if what == "update" else new / old
        print(f"{what:8s} medians old {old:.3f} new {new:.3f}: x{ratio:.2f}", flush=True)
    print(f"# load average {os.getloadavg()}")


if __name__ == "__main__":
    main()
