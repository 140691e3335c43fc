"""Train PPO on diacc with RLlib's PettingZoo support (one policy shared by the CAVs).

RLlib wraps a PettingZoo ``ParallelEnv`` in ``ParallelPettingZooEnv``; every
CAV maps to the one shared policy. Observations are diacc's ``"flat"``
format (RLlib's default encoders want a ``Box``). A tiny budget by default.

    pip install -e ".[rllib]"
    python examples/rllib_ppo.py --iterations 1
"""

from __future__ import annotations

import argparse

import ray
from ray.rllib.algorithms.ppo import PPOConfig
from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv
from ray.tune.registry import register_env

import diacc
from diacc.envs.env import AnnealTemperature

#: Env steps sampled per training iteration (``train_batch_size``).
BATCH_STEPS = 64


def make_env(config: dict) -> ParallelPettingZooEnv:
    env = diacc.parallel_env(
        observation_format="flat",
        map="train-50",
        scenario={"n_vehicles": 8, "cav_penetration": 0.25},
        sim={"episode_steps": 20},
    )
    # The budget in env steps, so that the team reward's temperature anneals over this
    # run as over a `diacc train` run (each env anneals by the steps it takes).
    return ParallelPettingZooEnv(AnnealTemperature(env, total_steps=config["total_steps"]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=1, help="RLlib training iterations")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False)
    register_env("diacc", make_env)
    config = (
        PPOConfig()
        .environment("diacc", env_config={"total_steps": BATCH_STEPS * args.iterations})
        .env_runners(num_env_runners=0)  # sample in this process: tiny and CI friendly
        .multi_agent(policies={"shared"}, policy_mapping_fn=lambda agent_id, *a, **k: "shared")
        .training(train_batch_size=BATCH_STEPS, minibatch_size=32, num_epochs=1)
        .debugging(seed=args.seed)
    )
    algo = config.build_algo()
    try:
        for iteration in range(1, args.iterations + 1):
            result = algo.train()
            steps = int(result["env_runners"]["num_env_steps_sampled_lifetime"])
            print(f"iteration {iteration}: {steps} env steps sampled in total")
    finally:
        algo.stop()
        ray.shutdown()


if __name__ == "__main__":
    main()
