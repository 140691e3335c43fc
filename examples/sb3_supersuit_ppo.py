"""Train PPO with parameter sharing on diacc through SuperSuit and Stable-Baselines3.

Every CAV is one entry of an SB3 vector env (SuperSuit's
``pettingzoo_env_to_vec_env``) and all CAVs share one policy. SB3 needs
observations of a fixed set of agents, while diacc's CAVs leave the road on
arrival: ``black_death_v3`` keeps a departed CAV in the vector with a zero
observation and reward. It needs ``Box`` observations, hence diacc's
``"flat"`` format. A tiny budget by default (CI runs it).

    pip install -e ".[sb3]"
    python examples/sb3_supersuit_ppo.py --steps 64
"""

from __future__ import annotations

import argparse

import supersuit as ss
from stable_baselines3 import PPO
from stable_baselines3.common.utils import set_random_seed

import diacc
from diacc.envs.env import AnnealTemperature


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=64, help="SB3 timesteps (agent steps)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    # SuperSuit's vector env has no seed(), so PPO(seed=...) fails: seed torch/numpy here;
    # diacc's episodes are seeded by the env itself (0, 1, 2, ... from the first reset).
    set_random_seed(args.seed)

    n_cavs = 2  # 8 vehicles, a quarter of them CAVs
    env = diacc.parallel_env(
        observation_format="flat",
        map="train-50",
        scenario={"n_vehicles": 8, "cav_penetration": 0.25},
        sim={"episode_steps": 20},
    )
    # The budget in env steps (each env step is one agent step per CAV), so that the team
    # reward's temperature anneals over this run as over a `diacc train` run.
    env = AnnealTemperature(env, total_steps=max(1, args.steps // n_cavs))
    env = ss.black_death_v3(env)
    vec_env = ss.pettingzoo_env_to_vec_env_v1(env)  # one entry per CAV
    vec_env = ss.concat_vec_envs_v1(vec_env, 1, num_cpus=0, base_class="stable_baselines3")
    n_steps = 16  # per vector entry; one update = n_steps x CAVs agent steps
    model = PPO(
        "MlpPolicy",
        vec_env,
        n_steps=n_steps,
        batch_size=n_steps * vec_env.num_envs,
        n_epochs=2,
        verbose=0,
    )
    model.learn(total_timesteps=args.steps)
    print(f"trained {model.num_timesteps} agent steps on {vec_env.num_envs} CAVs")
    observations = vec_env.reset()
    actions, _ = model.predict(observations, deterministic=True)
    print(f"greedy actions of the CAVs at reset: {actions.tolist()}")
    vec_env.close()


if __name__ == "__main__":
    main()
