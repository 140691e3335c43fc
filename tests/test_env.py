"""The multi-agent env on both backends: PettingZoo API, PSAR effect, batched API."""

from __future__ import annotations

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from diacc.envs.actions import ACCELERATE, LANE_LEFT, LANE_RIGHT, REMAIN
from diacc.envs.env import BottleneckEnv, EnvConfig
from diacc.envs.reward import team_reward
from diacc.sim.scenario import Scenario

BACKENDS = ["highway", "sumo"]

TWO_LANES = """
name = "two-lanes"
lane_width_m = 3.2
[[segments]]
kind = "multilane"
length_m = 400
lanes = 2
speed_limit_mps = 25.0
"""


@pytest.mark.parametrize("backend", BACKENDS)
def test_parallel_api(backend):
    config = EnvConfig(backend=backend, scenario=Scenario(n_vehicles=10, cav_penetration=0.3))
    env = BottleneckEnv(config)
    try:
        parallel_api_test(env, num_cycles=30)
    finally:
        env.close()


def _two_cav_episode(backend: str, use_psar: bool, tmp_path) -> tuple[int, int]:
    """Rear CAV cuts in 3 m behind the front CAV, then keeps accelerating."""
    road = tmp_path / "two.toml"
    road.write_text(TWO_LANES)
    env = BottleneckEnv(
        EnvConfig(
            backend=backend,
            map=str(road),
            use_psar=use_psar,
            scenario=Scenario(n_vehicles=2, cav_penetration=1.0),
        )
    )
    try:
        env.reset_arrays(seed=0)
        state = env.state_
        front, rear = np.argsort(-state.x_m[env.cav_index])  # agent slots
        toward = (
            LANE_LEFT
            if state.lane[env.cav_index[front]] > state.lane[env.cav_index[rear]]
            else LANE_RIGHT
        )
        collisions = 0
        for t in range(15):
            actions = np.full(2, REMAIN)
            actions[rear] = toward if t == 0 else ACCELERATE
            out = env.step_arrays(actions)
            collisions += len(out.state.collisions)
            if out.terminated:
                break
        return collisions, t + 1
    finally:
        env.close()


@pytest.mark.parametrize("backend", BACKENDS)
def test_psar_prevents_the_scripted_rear_end_collision(backend, tmp_path):
    without, steps_without = _two_cav_episode(backend, use_psar=False, tmp_path=tmp_path)
    with_psar, steps_with = _two_cav_episode(backend, use_psar=True, tmp_path=tmp_path)
    assert without >= 1 and steps_without < 15
    assert with_psar == 0 and steps_with == 15


@pytest.mark.parametrize("backend", BACKENDS)
def test_batched_api_shapes_and_reward(backend):
    env = BottleneckEnv(EnvConfig(backend=backend))
    try:
        actor, critic = env.reset_arrays(seed=3)
        assert actor.self_state.shape[0] == env.n_cavs == 10
        assert critic.nodes.shape == (40, actor.ego_hist.shape[-1])
        out = env.step_arrays(np.zeros(env.n_cavs, np.int64))
        assert (
            np.isfinite(env.reward_of(out)) and out.alive.shape == (10,) and out.ego.shape == (10,)
        )
        assert set(out.reward_terms) >= {"global", "completion", "individual", "delay"}
        # The temperature's parts are the trainer's (diacc.learn.mappo), not the env's.
        assert not {"ego_softmin", "tau"} & set(out.reward_terms)
        parts = (out.ego, out.alive, out.global_reward, out.completion, out.delay)
        team = team_reward(*parts, env.temperature, env.config.reward)
        assert env.reward_of(out) == team.total and env.temperature == env.config.reward.tau_init
        np.testing.assert_array_equal(out.actor_obs.action_memory[:, 0], 0)
    finally:
        env.close()


def test_same_seed_same_episode():
    env = BottleneckEnv(EnvConfig())
    rng = np.random.default_rng(0)
    actions = rng.integers(0, 5, (20, env.n_cavs))
    runs = []
    for _ in range(2):
        env.reset_arrays(seed=11)
        rewards = []
        for a in actions:
            out = env.step_arrays(a)
            rewards.append(env.reward_of(out))
            if out.terminated or out.truncated:
                break
        runs.append((rewards, out.state.x_m.copy()))
    env.close()
    assert runs[0][0] == runs[1][0]
    np.testing.assert_array_equal(runs[0][1], runs[1][1])


def test_pettingzoo_rewards_use_the_envs_own_temperature():
    """The env scores its PettingZoo rewards at :attr:`BottleneckEnv.temperature`
    (``tau_init``); a trainer that anneals tau makes the team reward from the terms."""
    env = BottleneckEnv(EnvConfig())
    actions = np.random.default_rng(1).integers(0, 5, (8, env.n_cavs))
    runs = {}
    try:
        for tau in (env.config.reward.tau_init, 0.05):
            env.temperature = tau
            env.reset_arrays(seed=4)
            steps = [env.step_arrays(a) for a in actions]
            runs[tau] = (steps, [env.reward_of(out) for out in steps])
    finally:
        env.close()
    (hot, hot_rewards), (cold, cold_rewards) = runs.values()
    for a, b in zip(hot, cold, strict=True):
        np.testing.assert_array_equal(a.ego, b.ego)  # the terms need no temperature
        assert (a.global_reward, a.completion, a.delay) == (b.global_reward, b.completion, b.delay)
    assert hot_rewards != cold_rewards
