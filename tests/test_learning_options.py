"""The learning-path options (docs/concepts/learning-options.md) in tiny training runs."""

from __future__ import annotations

import json

import numpy as np
import torch
from test_mappo import rollout_batch, tiny_config

from diacc.config import override
from diacc.experiments.policies import CheckpointPolicy
from diacc.learn.mappo import train
from diacc.learn.ppo import evaluate_batch

ALL_OPTIONS = {
    "critic_values": "per_agent",
    "env.psar_actions": "masked",
    "env.reward.closeness": "bumper",
    "env.reward.exit_bonus_scale": "fleet",
    "env.reward.delay_weight": 1.0,
    "env.obs.critic_step_input": False,
    "env.obs.road_speed_limits": True,
}


def test_per_agent_values_and_masked_actions_replay_exactly(tmp_path):
    cfg = override(tiny_config(tmp_path), ALL_OPTIONS)
    agent, roll, batch = rollout_batch(cfg)
    E, C = cfg.n_envs, 4
    assert roll.values.shape == (cfg.rollout_steps, E, C)
    assert batch.returns.shape == (cfg.chunk_len, 2 * E, C)
    # Slots' values differ: the head sees each CAV's own features.
    assert np.abs(np.diff(roll.values, axis=-1)).max() > 0
    # Sampled actions are always allowed by the mask they were sampled under.
    mask = np.stack([obs.action_mask for obs in roll.actor_obs])  # (S, E, C, 5)
    taken = np.take_along_axis(mask, roll.actions[..., None], axis=-1)[..., 0]
    assert taken.all() and not mask.all()
    with torch.no_grad():
        every_env = torch.arange(batch.critic_h0.shape[0])
        logprob, entropy, values, agents = evaluate_batch(agent, batch, every_env, C)
    alive = batch.alive[:, agents].bool()  # a replay need not encode CAVs off the road
    ratio = (logprob - batch.logprobs[:, agents]).exp()[alive]
    assert torch.allclose(ratio, torch.ones_like(ratio), atol=1e-5)
    assert torch.allclose(values, batch.old_values_normalised, atol=1e-5)
    assert torch.isfinite(entropy).all()


def test_executed_mode_trains_on_what_psar_executed(tmp_path):
    cfg = override(tiny_config(tmp_path), {"env.psar_actions": "executed"})
    agent, roll, batch = rollout_batch(cfg)
    # The stored action of step t is the refined action the env remembered at t + 1.
    for t in range(cfg.rollout_steps - 1):
        carried = ~roll.episode_start[t + 1]  # (E,)
        executed = roll.actor_obs[t + 1].action_memory[..., 1]  # (E, C) refined at t
        assert (roll.actions[t][carried] == executed[carried]).all()
    with torch.no_grad():
        logprob, _, _, agents = evaluate_batch(agent, batch, torch.arange(2 * cfg.n_envs), 4)
    alive = batch.alive[:, agents].bool()  # a replay need not encode CAVs off the road
    assert torch.allclose(logprob[alive], batch.logprobs[:, agents][alive], atol=1e-5)


def test_tiny_training_with_every_option_and_masked_evaluation(tmp_path):
    cfg = override(tiny_config(tmp_path), ALL_OPTIONS)
    run = train(cfg, progress=False)
    rows = [json.loads(line) for line in (run / "progress.jsonl").read_text().splitlines()]
    assert len(rows) == 2 and all(np.isfinite(r["value_loss"]) for r in rows)
    policy = CheckpointPolicy(run / "checkpoint.pt")
    assert policy.train_config.critic_values == "per_agent"
    from diacc.envs.env import BottleneckEnv

    env = BottleneckEnv(policy.base)
    actor, _ = env.reset_arrays(seed=5)
    policy.begin_episode(env.n_cavs, 5)
    for step in range(10):
        actions = policy.act(actor, step == 0)  # greedy, restricted to the mask
        assert np.take_along_axis(actor.action_mask, actions[:, None], axis=-1).all()
        actor = env.step_arrays(actions).actor_obs
    env.close()


def test_per_agent_gae_is_the_team_gae_of_each_slot():
    """GAE per agent = the team GAE run on each slot's values, with the shared reward."""
    from diacc.config import TrainConfig
    from diacc.learn.buffer import Rollout, compute_gae
    from diacc.learn.ppo import rollout_gae

    rng = np.random.default_rng(0)
    S, E, C = 6, 2, 3
    roll = Rollout.allocate(S, E, C, 1, 1, per_agent=True)
    roll.rewards[:] = rng.normal(size=(S, E))
    roll.values[:] = rng.normal(size=(S, E, C))
    roll.final_values[:] = rng.normal(size=(S, E, C))
    roll.terminated[2, 0] = roll.truncated[4, 1] = True
    next_value = rng.normal(size=(E, C))
    cfg = TrainConfig(gamma=0.9, gae_lambda=0.8)
    adv, ret = rollout_gae(roll, next_value, cfg)
    assert adv.shape == (S, E, C)
    for c in range(C):
        team_adv, team_ret = compute_gae(
            roll.rewards,
            roll.values[..., c],
            next_value[:, c],
            roll.terminated,
            roll.truncated,
            roll.final_values[..., c],
            0.9,
            0.8,
        )
        np.testing.assert_allclose(adv[..., c], team_adv)
        np.testing.assert_allclose(ret[..., c], team_ret)
    # Hand check of the last step of env 0 (no episode end): delta = r + gamma V' - V.
    delta = roll.rewards[-1, 0] + 0.9 * next_value[0] - roll.values[-1, 0]
    np.testing.assert_allclose(adv[-1, 0], delta)


def test_own_credit_gives_each_cav_its_reward_and_ends_its_returns_at_its_crash(tmp_path):
    """``credit = "own"``: a crashing CAV's own reward carries the crash penalty, its returns
    end there (its GAE does not reach past it) and the others' rewards do not carry it."""
    from diacc.learn.ppo import rollout_gae

    cfg = override(
        tiny_config(tmp_path),
        {
            "variant": "diacc-nopsar",
            "critic_values": "per_agent",
            "credit": "own",
            "env.sim.on_collision": "remove",
            "env.reward.crash_penalty": 50.0,
            "env.map": "train-50",
            "env.sim.episode_steps": 20,
        },
    )
    _, roll, _ = rollout_batch(cfg)
    crashed = roll.agent_rewards < -40.0  # (S, E, C) a crash step of that CAV
    assert crashed.any(), "no CAV crashed in the tiny rollout: pick another seed"
    assert roll.agent_ended[crashed].all()
    # The team reward charged the crash to the env; the own rewards of the others do not.
    t, e, c = np.argwhere(crashed)[0]
    others = np.delete(roll.agent_rewards[t, e], np.flatnonzero(crashed[t, e]))
    assert (others > -40.0).all()
    adv, ret = rollout_gae(roll, np.zeros(roll.values.shape[1:]), cfg)
    # Terminated: its return at the crash step is its own reward, no bootstrap.
    np.testing.assert_allclose(ret[t, e, c], roll.agent_rewards[t, e, c])


def test_own_credit_needs_per_agent_values(tmp_path):
    import pytest

    from diacc.config import ConfigError, validate

    with pytest.raises(ConfigError, match="per_agent"):
        validate(override(tiny_config(tmp_path), {"credit": "own"}))
