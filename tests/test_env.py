"""The multi-agent env on both backends: PettingZoo API, PSAR effect, batched API."""

from __future__ import annotations

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from diacc.envs.actions import ACCELERATE, DECELERATE, LANE_LEFT, LANE_RIGHT, REMAIN
from diacc.envs.env import AnnealTemperature, BottleneckEnv, EnvConfig
from diacc.envs.reward import RewardError, team_reward, temperature
from diacc.sim.scenario import Scenario
from diacc.sim.settings import SimConfig

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
        state = env.state_  # a batch of one env
        front, rear = np.argsort(-state.x_m[0, env.cav_index])  # agent slots
        toward = (
            LANE_LEFT
            if state.lane[0, env.cav_index[front]] > state.lane[0, env.cav_index[rear]]
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
@pytest.mark.parametrize("scale", [1.0, 2.0])
def test_decelerate_lowers_the_speed_by_the_scaled_step(backend, scale, tmp_path):
    """Without PSAR, *decelerate* brakes by ``speed_change_mps x decelerate_scale`` per step
    (the paper's 2 m/s at the default 1; 4 m/s at 2, within the CAV's 5 m/s^2)."""
    road = tmp_path / "two.toml"
    road.write_text(TWO_LANES)
    sim = SimConfig(decelerate_scale=scale)
    config = EnvConfig(
        backend=backend,
        map=str(road),
        use_psar=False,
        sim=sim,
        scenario=Scenario(n_vehicles=2, cav_penetration=1.0),
    )
    env = BottleneckEnv(config)
    try:
        env.reset_arrays(seed=0)
        for _ in range(3):  # from the release speed (10 m/s) to 16
            env.step_arrays(np.full(2, ACCELERATE))
        before = env.state_.speed_mps[0, env.cav_index].copy()
        after = env.step_arrays(np.full(2, DECELERATE)).state.speed_mps[0, env.cav_index]
        assert before == pytest.approx([16.0, 16.0], abs=0.05)
        assert after == pytest.approx(before - 2.0 * scale, abs=0.05)
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
        assert np.isfinite(out.reward) and out.alive.shape == (10,) and out.ego.shape == (10,)
        logged = env.transition.reward_terms  # of the batch of one the env stepped
        assert set(logged) >= {"global", "completion", "individual", "delay"}
        # The first step of training: R at tau_init, from the terms the step carries.
        parts = (out.ego, out.alive, out.global_reward, out.completion, out.delay)
        assert (
            out.reward == team_reward(*parts, env.config.reward.tau_init, env.config.reward).total
        )
        assert env.tau == env.config.reward.tau_init  # the env counts nothing
        np.testing.assert_array_equal(out.actor_obs.action_memory[:, 0], 0)
    finally:
        env.close()


def test_the_step_is_a_batch_of_one_unbatched_at_the_pettingzoo_edge():
    env = BottleneckEnv(EnvConfig())
    try:
        env.reset_arrays(seed=3)
        out = env.step_arrays(np.zeros(env.n_cavs, np.int64))
        batch = env.transition  # the batch of one the env stepped, scored
        assert batch.terminated.shape == (1,) and batch.reward.shape == (1,)
        assert isinstance(out.terminated, bool) and out.reward == batch.reward[0]
        np.testing.assert_array_equal(out.actor_obs.self_state, batch.actor_obs.self_state[0])
        assert out.state.x_m.shape == (1, env.batch.state.traffic.n_vehicles)  # kept a batch
        unscored = env.batch.step(np.zeros((1, env.n_cavs), np.int64))
        with pytest.raises(ValueError, match="no team reward yet"):
            _ = unscored.reward
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
            rewards.append(out.reward)
            if out.terminated or out.truncated:
                break
        runs.append((rewards, out.state.x_m.copy()))
    env.close()
    assert runs[0][0] == runs[1][0]
    np.testing.assert_array_equal(runs[0][1], runs[1][1])


def test_anneal_temperature_sets_the_schedules_tau_before_each_step():
    """Through :class:`AnnealTemperature` each step's reward (array and PettingZoo API
    alike) is the team reward at the schedule's temperature at the env steps taken through
    it (tau_init -> tau_final over half of ``total_steps``); the bare env stays at its tau."""
    cfg = EnvConfig(
        scenario=Scenario(n_vehicles=8, cav_penetration=0.5), sim=SimConfig(episode_steps=5)
    )
    arrays = AnnealTemperature(BottleneckEnv(cfg), total_steps=8)
    zoo = AnnealTemperature(BottleneckEnv(cfg), total_steps=8)
    bare = BottleneckEnv(cfg)
    actions = np.random.default_rng(1).integers(0, 5, (6, arrays.n_cavs))
    try:
        arrays.reset_arrays(seed=4)
        zoo.reset(seed=4)
        bare.reset_arrays(seed=4)
        taus = []
        for t, a in enumerate(actions):
            agents = list(zoo.agents)
            out = arrays.step_arrays(a)
            _, rewards, *_ = zoo.step({agent: int(a[zoo.agent_slots()[agent]]) for agent in agents})
            taus.append(temperature(t, 8, cfg.reward))
            parts = (out.ego, out.alive, out.global_reward, out.completion, out.delay)
            assert out.reward == team_reward(*parts, taus[-1], cfg.reward).total
            assert set(rewards.values()) == {out.reward}
            assert (arrays.steps, zoo.steps) == (t + 1, t + 1)
            alone = bare.step_arrays(a)
            assert alone.reward == team_reward(*parts, cfg.reward.tau_init, cfg.reward).total
            if out.terminated or out.truncated:
                break
        assert taus == pytest.approx([2.0, 1.5125, 1.025, 0.5375, 0.05])
        assert zoo.step({}) == ({}, {}, {}, {}, {})  # after the end: simulates nothing,
        assert zoo.steps == 5  # counts nothing
    finally:
        for env in (arrays, zoo, bare):
            env.close()
    for bad in (0, -3, 2.5, True):
        with pytest.raises(RewardError, match="total_steps"):
            AnnealTemperature(bare, bad)


def test_parallel_env_names_the_wrapper_when_given_a_schedule_length():
    import diacc
    from diacc.config import ConfigError

    with pytest.raises(ConfigError, match="AnnealTemperature"):
        diacc.parallel_env(total_steps=100)
