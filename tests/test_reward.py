"""Tests of diacc.envs.reward against hand computations, and of the team reward's aggregation."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers import make_state, one_env

from diacc.config import ConfigError, RewardConfig, TrainConfig, override
from diacc.envs.reward import (
    RewardError,
    RewardTerms,
    reward_terms,
    softmin_weights,
    team_reward,
    temperature,
)
from diacc.sim.maps import load_map

# The tests below read one env: (C,) arrays in and out of an E = 1 batch.
reward_terms = one_env(reward_terms)

CFG = RewardConfig()
ROAD = load_map("train-25")  # 25 m/s everywhere


def sigmoid(z: float) -> float:
    return 1.0 / (1.0 + math.exp(-z))


def team(terms: RewardTerms, tau: float, cfg: RewardConfig = CFG):
    """The team reward of ``terms`` at ``tau``."""
    return team_reward(
        terms.ego, terms.alive, terms.global_reward, terms.completion, terms.delay, tau, cfg
    )


# ---------------------------------------------------------------- softmin
def test_softmin_weights_sum_to_one_over_alive_agents():
    r = np.array([1.0, -2.0, 3.0, 0.5])
    alive = np.array([True, True, False, True])
    for tau in (0.05, 0.5, 2.0, 50.0):
        w = softmin_weights(r, alive, tau)
        assert w.sum() == pytest.approx(1.0)
        assert w[2] == 0.0
    w = softmin_weights(r, alive, 1.0)
    e = np.exp(-np.array([1.0, -2.0, 0.5]))
    assert w[[0, 1, 3]] == pytest.approx(e / e.sum())


def test_softmin_concentrates_on_worst_agent_as_tau_shrinks():
    r = np.array([4.0, 1.0, 3.0])
    w = softmin_weights(r, np.ones(3, bool), 1e-3)
    assert w == pytest.approx([0.0, 1.0, 0.0])
    w_mid = softmin_weights(r, np.ones(3, bool), 0.5)
    assert w_mid[1] > w_mid[2] > w_mid[0]
    # stable with huge rewards / tiny tau (no overflow, no nan)
    w = softmin_weights(np.array([1e6, -1e6]), np.ones(2, bool), 1e-6)
    assert np.isfinite(w).all() and w.tolist() == [0.0, 1.0]


def test_softmin_becomes_uniform_as_tau_grows():
    w = softmin_weights(np.array([4.0, 1.0, 3.0, -2.0]), np.ones(4, bool), 1e6)
    assert w == pytest.approx(np.full(4, 0.25), abs=1e-5)


def test_softmin_without_alive_agents_and_bad_tau():
    assert softmin_weights(np.array([1.0, 2.0]), np.zeros(2, bool), 1.0).tolist() == [0.0, 0.0]
    assert softmin_weights(np.zeros(0), np.zeros(0, bool), 1.0).shape == (0,)  # no CAV slots
    batch = softmin_weights(
        np.array([[1.0, 2.0], [1.0, 2.0]]), np.array([[True, True], [False] * 2]), 1.0
    )
    assert batch[0].sum() == pytest.approx(1.0) and batch[1].tolist() == [0.0, 0.0]
    with pytest.raises(RewardError, match="temperature"):
        softmin_weights(np.array([1.0]), np.ones(1, bool), 0.0)


# ---------------------------------------------------------------- tau schedule
def test_temperature_schedule_endpoints_and_midpoint():
    assert temperature(0, 1000, CFG) == pytest.approx(2.0)
    assert temperature(250, 1000, CFG) == pytest.approx(2.0 - 1.95 * 0.5)
    assert temperature(500, 1000, CFG) == pytest.approx(0.05)
    assert temperature(900, 1000, CFG) == pytest.approx(0.05)
    with pytest.raises(RewardError, match="total_steps"):
        temperature(0, 0, CFG)


def test_vector_envs_emit_the_team_reward_at_the_temperature_they_are_given():
    """``Transition.team`` is :func:`team_reward` of the step's terms at the envs' ``tau``
    (``tau_init`` until set): the envs count no steps, the trainer sets it."""
    from diacc.config import EnvConfig
    from diacc.envs.vector import make_vector_env

    envs = make_vector_env(EnvConfig(), 3, 7, "batched")
    rng = np.random.default_rng(0)
    try:
        envs.reset(first_episode=0)
        for tau in (None, None, 0.3, 0.05, 0.05):
            if tau is None:
                tau = CFG.tau_init  # not set
            else:
                envs.tau = tau
            out = envs.step(rng.integers(0, 5, (3, envs.n_cavs)))
            parts = (out.ego, out.alive, out.global_reward, out.completion, out.delay)
            np.testing.assert_array_equal(out.team.total, team_reward(*parts, tau, CFG).total)
            assert envs.tau == tau
    finally:
        envs.close()


# ---------------------------------------------------------------- ego terms
def test_speed_and_time_penalty_terms():
    state = make_state([100.0, 300.0], [0, 1], [20.0, 4.0], is_cav=True)
    terms = reward_terms(state, np.array([0, 1]), ROAD, CFG)
    assert terms.speed == pytest.approx([-5.0 / 25.0 + 1.0, -21.0 / 25.0 + 1.0])
    assert terms.time_penalty == pytest.approx([sigmoid(15.0) - 1.0, sigmoid(-1.0) - 1.0])
    assert terms.warning.tolist() == [0.0, 0.0] and terms.collision.tolist() == [0.0, 0.0]
    expected = 5.0 * terms.speed + terms.time_penalty
    assert terms.ego == pytest.approx(expected)


def test_warning_and_collision_terms_by_centre_distance():
    # CAV 0 at (100, 1.6); HDV 1 at 2.5 m ahead (warning only); HDV 2 at 1.2 m
    # (warning and collision); HDV 3 3.2 m to the side (outside d_w = 3); HDV 4
    # inactive at 0.5 m (ignored).
    x = [100.0, 102.5, 98.8, 100.0, 100.5]
    lane = [0, 0, 0, 1, 0]
    state = make_state(
        x, lane, 25.0, is_cav=[True, False, False, False, False], active=[True] * 4 + [False]
    )
    terms = reward_terms(state, np.array([0]), ROAD, CFG)
    d_w, d_c = 3.0, 1.5
    warning = -(d_w - 2.5) / (d_w - d_c) - (d_w - 1.2) / (d_w - d_c)
    collision = -(d_c - 1.2) / d_c - 10.0
    assert terms.warning[0] == pytest.approx(warning)
    assert terms.collision[0] == pytest.approx(collision)
    time_pen = sigmoid(20.0) - 1.0
    assert terms.ego[0] == pytest.approx(5.0 * 1.0 + 0.5 * warning + 1.0 * collision + time_pen)


def test_reported_collision_adds_fixed_penalty_beyond_collision_distance():
    state = make_state([100.0, 104.0], [0, 0], 20.0, is_cav=[True, False], collisions=[(1, 0)])
    terms = reward_terms(state, np.array([0]), ROAD, CFG)
    assert terms.collision[0] == pytest.approx(-10.0)  # distance part clipped at 0
    assert terms.warning[0] == 0.0  # 4 m > d_w


# ---------------------------------------------------------------- total
def test_total_reward_combines_softmin_global_and_completion():
    # CAVs 0, 1 on the road, CAV 2 arrived this step, HDV 3 arrived too (no bonus)
    state = make_state(
        [100.0, 400.0, 1300.0, 1300.0],
        [0, 1, 2, 3],
        [10.0, 22.0, 25.0, 25.0],
        is_cav=[True, True, True, False],
        active=[True, True, False, False],
        arrived=[False, False, True, True],
        segment=[0, 0, 2, 2],
        arrivals=[2, 3],
    )
    tau = 0.7
    terms = reward_terms(state, np.array([0, 1, 2]), ROAD, CFG)
    total = team(terms, tau)
    r0 = 5.0 * (1 - 15 / 25) + sigmoid(5.0) - 1.0
    r1 = 5.0 * (1 - 3 / 25) + sigmoid(17.0) - 1.0
    assert terms.ego == pytest.approx([r0, r1, 0.0])
    assert terms.alive.tolist() == [True, True, False]
    w0 = math.exp(-r0 / tau) / (math.exp(-r0 / tau) + math.exp(-r1 / tau))
    assert total.softmin_weight == pytest.approx([w0, 1 - w0, 0.0])
    ego_bar = w0 * r0 + (1 - w0) * r1
    r_g = -abs(16.0 - 25.0) / 25.0 + 1.0
    assert total.ego_softmin == pytest.approx(ego_bar)
    assert terms.global_reward == pytest.approx(r_g)
    assert terms.completion == pytest.approx(20.0)
    assert total.total == pytest.approx(0.6 * ego_bar + 0.4 * r_g + 20.0)


def test_no_cav_on_road_gives_only_completion():
    state = make_state(
        [1300.0, 1300.0],
        [0, 1],
        25.0,
        is_cav=True,
        active=False,
        arrived=True,
        segment=2,
        arrivals=[0, 1],
    )
    terms = reward_terms(state, np.array([0, 1]), ROAD, CFG)
    total = team(terms, 1.0)
    assert total.ego_softmin == 0.0 and terms.global_reward == 0.0
    assert total.total == pytest.approx(40.0)


def test_reward_config_rejects_bad_distances():
    # checked once when the config is built, not on every reward call
    with pytest.raises(ConfigError, match="collision_distance_m < warning_distance_m"):
        RewardConfig(collision_distance_m=5.0)
    with pytest.raises(ConfigError, match="'env.reward.tau_anneal_fraction' must be in"):
        override(TrainConfig(), {"env.reward.tau_anneal_fraction": 0})


# ---------------------------------------------------------------- options (docs)
def test_bumper_closeness_uses_lane_gaps_and_leader_ttc():
    # CAV 0 at x=100 lane 0 at 20 m/s; leader HDV 1 at x=107.5 (gap 2.5 m) at 10 m/s;
    # HDV 2 in lane 1 alongside (centre 3.2 m: outside d_w under "centre" too);
    # follower HDV 3 at x=94 (gap 1.0 m, inside d_c). Only 1 and 3 count.
    state = make_state(
        [100.0, 107.5, 100.0, 94.0],
        [0, 0, 1, 0],
        [20.0, 10.0, 20.0, 20.0],
        is_cav=[True] + [False] * 3,
    )
    cfg = RewardConfig(closeness="bumper", warning_ttc_s=3.0)
    terms = reward_terms(state, np.array([0]), ROAD, cfg)
    d_w, d_c = 3.0, 1.5
    ttc = 2.5 / 10.0  # gap / closing speed
    warning = -(d_w - 2.5) / (d_w - d_c) - (d_w - 1.0) / (d_w - d_c) - (3.0 - ttc) / 3.0
    assert terms.warning[0] == pytest.approx(warning)
    assert terms.collision[0] == pytest.approx(-(d_c - 1.0) / d_c - 10.0)
    # The paper's centre distances: 7.5, 3.2 and 6 m, nothing fires.
    literal = reward_terms(state, np.array([0]), ROAD, CFG)
    assert literal.warning[0] == 0.0 and literal.collision[0] == 0.0


def test_bumper_closeness_quiet_without_close_vehicles():
    state = make_state([100.0, 140.0], [0, 0], [20.0, 25.0], is_cav=[True, False])
    terms = reward_terms(state, np.array([0]), ROAD, RewardConfig(closeness="bumper"))
    assert terms.warning[0] == 0.0 and terms.collision[0] == 0.0  # 35 m gap, opening


def test_fleet_exit_bonus_and_delay_term():
    # 4 CAV slots, one arrives; HDV at 15 m/s and CAV at 25 m/s on a 25 m/s road.
    state = make_state(
        [100.0, 200.0, 300.0, 400.0, 500.0],
        [0, 0, 0, 0, 1],
        [25.0, 25.0, 25.0, 25.0, 15.0],
        is_cav=[True, True, True, True, False],
        active=[False, True, True, True, True],
        arrived=[True, False, False, False, False],
        arrivals=[0],
    )
    cav = np.array([0, 1, 2, 3])
    per_cav = reward_terms(state, cav, ROAD, CFG)
    fleet = reward_terms(state, cav, ROAD, RewardConfig(exit_bonus_scale="fleet"))
    assert per_cav.completion == pytest.approx(20.0) and fleet.completion == pytest.approx(5.0)
    rate = (1.0 - 15.0 / 25.0) / 5  # only the HDV is slower than the limit; V = 5
    assert per_cav.delay == pytest.approx(-rate)  # logged, but weight 0 by default
    delayed_cfg = RewardConfig(delay_weight=2.0)
    delayed = reward_terms(state, cav, ROAD, delayed_cfg)
    assert team(delayed, 1.0, delayed_cfg).total == pytest.approx(
        team(per_cav, 1.0).total - 2.0 * rate
    )


def test_reward_options_rejected_when_unknown():
    from diacc.config import ConfigError

    with pytest.raises(ConfigError, match="closeness"):
        RewardConfig(closeness="overlap")
    with pytest.raises(ConfigError, match="exit_bonus_scale"):
        RewardConfig(exit_bonus_scale="half")


# ---------------------------------------------------------------- team reward (aggregation)
def _old_team_reward(ego, alive, global_reward, completion, delay, tau, cfg):
    """The aggregation as ``reward()`` did it for one env before the temperature moved to
    the learner (its lines, copied): weights, ego_softmin and total."""
    weights = softmin_weights(ego, alive, tau)  # (..., C)
    ego_softmin = np.sum(weights * ego, axis=-1)  # (...,)
    total = (
        cfg.w_ego * ego_softmin
        + cfg.w_global * global_reward
        + completion
        + cfg.delay_weight * delay
    )
    return weights, float(ego_softmin), float(total)


def test_team_reward_of_a_batch_equals_per_env_calls_and_the_old_total():
    rng = np.random.default_rng(7)
    cfg = RewardConfig(w_ego=0.7, w_global=0.3, delay_weight=1.5)
    for shape in ((5, 10), (2, 3, 4)):
        alive = rng.random(shape) < 0.6
        alive[0] = False  # an env without CAVs on the road
        ego = np.where(alive, rng.normal(0.0, 4.0, shape), 0.0)
        lead = shape[:-1]
        g, c, d = rng.normal(size=lead), 20.0 * rng.integers(0, 3, lead), -rng.random(lead)
        for tau in (2.0, 0.3, 0.05):
            batch = team_reward(ego, alive, g, c, d, tau, cfg)
            assert batch.softmin_weight.shape == shape and batch.total.shape == lead
            for idx in np.ndindex(*lead):
                one = team_reward(ego[idx], alive[idx], float(g[idx]), c[idx], d[idx], tau, cfg)
                assert one.total.shape == one.ego_softmin.shape == ()  # one env: 0-d
                old = _old_team_reward(
                    ego[idx], alive[idx], np.asarray(g[idx]), c[idx], d[idx], tau, cfg
                )
                # bit for bit: per env, in the batch, and as before the split
                assert np.array_equal(one.softmin_weight, old[0])
                assert (one.ego_softmin, one.total) == old[1:]
                assert np.array_equal(batch.softmin_weight[idx], one.softmin_weight)
                assert (batch.ego_softmin[idx], batch.total[idx]) == (one.ego_softmin, one.total)
    with pytest.raises(RewardError, match="temperature"):
        team_reward(np.zeros(2), np.ones(2, bool), 0.0, 0.0, 0.0, 0.0, cfg)


def test_team_reward_depends_on_the_temperature_only_through_the_softmin():
    state = make_state([100.0, 400.0], [0, 1], [10.0, 22.0], is_cav=True)
    terms = reward_terms(state, np.array([0, 1]), ROAD, CFG)
    hot, cold = team(terms, CFG.tau_init), team(terms, CFG.tau_final)
    assert cold.ego_softmin < hot.ego_softmin < terms.ego.mean() + 1e-12  # worst CAV weighs more
    assert hot.total - cold.total == pytest.approx(CFG.w_ego * (hot.ego_softmin - cold.ego_softmin))
