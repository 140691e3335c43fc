"""Train MAPPO on diacc with TorchRL: ``PettingZooWrapper`` + ``ClipPPOLoss``.

A tiny budget by default (CI runs it); raise ``--iterations`` and
``--frames`` for a real run. Observations are diacc's ``"flat"`` format, one
float32 vector per CAV, so TorchRL's ``MultiAgentMLP`` reads them directly;
the critic is centralised (MAPPO; ``--ippo`` for a decentralised one).
Dead agents are masked by the wrapper (``use_mask=True``): a CAV that has
left the road stays in the tensors with a zero observation.

    pip install -e ".[torchrl]"
    python examples/torchrl_mappo.py --iterations 2 --frames 40
"""

from __future__ import annotations

import argparse

import torch
from tensordict.nn import TensorDictModule
from torch.distributions import Categorical
from torchrl.collectors import Collector
from torchrl.envs.libs.pettingzoo import PettingZooWrapper
from torchrl.modules import MultiAgentMLP, ProbabilisticActor
from torchrl.objectives import ClipPPOLoss, ValueEstimators

import diacc
from diacc.envs.env import AnnealTemperature

GROUP = "cav"  # the wrapper groups agents by the name before "_": cav_0, cav_1 -> "cav"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=2, help="collect + update rounds")
    parser.add_argument("--frames", type=int, default=40, help="env steps per iteration")
    parser.add_argument("--ippo", action="store_true", help="decentralised critic (IPPO)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.manual_seed(args.seed)

    zoo_env = diacc.parallel_env(
        observation_format="flat",
        map="train-50",
        scenario={"n_vehicles": 8, "cav_penetration": 0.25},
        sim={"episode_steps": 20},
    )
    # The budget in env steps, so that the team reward's temperature anneals over this
    # run as over a `diacc train` run.
    zoo_env = AnnealTemperature(zoo_env, total_steps=args.frames * args.iterations)
    env = PettingZooWrapper(zoo_env, use_mask=True, categorical_actions=True, seed=args.seed)
    n_agents = len(env.group_map[GROUP])
    obs_key, action_key = (GROUP, "observation"), env.action_key
    obs_dim = env.observation_spec[obs_key].shape[-1]  # (n_agents, D)
    n_actions = env.full_action_spec[action_key].space.n

    actor_net = MultiAgentMLP(
        n_agent_inputs=obs_dim,
        n_agent_outputs=n_actions,
        n_agents=n_agents,
        centralised=False,
        share_params=True,
        depth=2,
        num_cells=64,
    )
    policy = ProbabilisticActor(
        TensorDictModule(actor_net, in_keys=[obs_key], out_keys=[(GROUP, "logits")]),
        in_keys=[(GROUP, "logits")],
        out_keys=[action_key],
        spec=env.full_action_spec[action_key],
        distribution_class=Categorical,
        return_log_prob=True,
    )
    critic_net = MultiAgentMLP(
        n_agent_inputs=obs_dim,
        n_agent_outputs=1,
        n_agents=n_agents,
        centralised=not args.ippo,  # MAPPO: every agent's value sees all observations
        share_params=True,
        depth=2,
        num_cells=64,
    )
    critic = TensorDictModule(critic_net, in_keys=[obs_key], out_keys=[(GROUP, "state_value")])

    loss = ClipPPOLoss(policy, critic, clip_epsilon=0.2, entropy_coeff=0.01)
    loss.set_keys(
        reward=env.reward_key,
        action=action_key,
        value=(GROUP, "state_value"),
        done=(GROUP, "done"),
        terminated=(GROUP, "terminated"),
    )
    loss.make_value_estimator(ValueEstimators.GAE, gamma=0.99, lmbda=0.95)
    optimizer = torch.optim.Adam(loss.parameters(), lr=3e-4)
    collector = Collector(
        env,
        policy,
        frames_per_batch=args.frames,
        total_frames=args.frames * args.iterations,
        auto_register_policy_transforms=True,
    )
    for iteration, data in enumerate(collector, start=1):
        with torch.no_grad():
            loss.value_estimator(data, params=loss.critic_network_params, target_params=None)
        terms = loss(data)
        total = terms["loss_objective"] + terms["loss_critic"] + terms["loss_entropy"]
        optimizer.zero_grad()
        total.backward()
        optimizer.step()
        reward = data.get(("next", *env.reward_key)).mean().item()
        print(
            f"iteration {iteration}: {data.numel()} env steps, mean team reward {reward:.3f}, "
            f"loss {total.item():.3f}"
        )
    collector.shutdown()
    env.close()


if __name__ == "__main__":
    main()
