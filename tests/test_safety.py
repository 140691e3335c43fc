"""Tests of diacc.envs.safety (neighbour search, gap/TTC, events) and diacc.envs.psar
(Algorithm 1)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers import first_env, make_state, one_env

from diacc.config import ConfigError, EventConfig, PSARConfig
from diacc.envs.actions import ACCELERATE, DECELERATE, LANE_LEFT, LANE_RIGHT, REMAIN
from diacc.envs.psar import (
    CANCEL_LC,
    DECEL_LC,
    FORCE_BRAKE,
    RULE_BITS,
    RULE_NONE,
    SUPPR_ACCEL,
    psar,
    rule_counts,
)
from diacc.envs.safety import (
    SafetyError,
    lane_leaders_followers,
    pair_kinematics,
    safety_critical_events,
    waiting_events,
)
from diacc.sim.maps import load_map

# The tests below read one env: (C,) arrays in and out of an E = 1 batch.
psar = one_env(psar)
lane_leaders_followers = one_env(lane_leaders_followers)
pair_kinematics = one_env(pair_kinematics)
safety_critical_events = one_env(safety_critical_events)
waiting_events = one_env(waiting_events)

# Algorithm 1 read literally (fixed thresholds, Force-Brake = action 4): the cases below
# check the pseudocode line by line; the default options are tested further down.
CFG = PSARConfig(force_brake="paper", horizon="paper", coordinate_lane_changes=False)
# d_lc_min 1, d_safe 5, d_warn 8, d_att 15 m; TTC 2 / 3 / 5 s; b_max 2
ROAD = load_map("train-25")  # 4 lanes, lane 3 missing in segment 1 (500-800 m)
EGO_X, EGO_V = 100.0, 20.0  # the CAV (index 0) in every PSAR case, 5 m long


def run_psar(others: list[tuple[float, int, float]], action: int, ego_lane: int = 1, **kw):
    """PSAR for CAV 0 at (EGO_X, ego_lane, EGO_V) among (x, lane, speed) others."""
    x = [EGO_X] + [o[0] for o in others]
    lane = [ego_lane] + [o[1] for o in others]
    speed = [EGO_V] + [o[2] for o in others]
    state = make_state(x, lane, speed, is_cav=[True] + [False] * len(others), **kw)
    return psar(state, np.array([0]), np.array([action]), CFG, ROAD)


def check(res, action: int, rule: int, mask: int | None = None, decel: float = 0.0) -> None:
    assert res.action.tolist() == [action]
    assert res.rule.tolist() == [rule]
    expected_mask = (RULE_BITS[rule] if rule else 0) if mask is None else mask
    assert res.rule_mask.tolist() == [expected_mask]
    assert res.decel_lc_mps2 == pytest.approx([decel])


# ---------------------------------------------------------------- neighbours
def test_neighbour_search_picks_nearest_front_and_rear_per_lane():
    #        0 ego  1      2      3     4     5(off) 6      7      8
    x = [100.0, 120.0, 110.0, 90.0, 50.0, 105.0, 130.0, 100.0, 99.0]
    lane = [1, 1, 1, 1, 1, 2, 2, 0, 0]
    active = [True, True, True, True, True, False, True, True, True]
    state = make_state(x, lane, active=active)
    nb = lane_leaders_followers(state, np.array([0, 7]))
    # columns: right, same, left
    assert nb.front.tolist() == [[7, 2, 6], [-1, -1, 0]]
    assert nb.rear.tolist() == [[8, 3, -1], [-1, 8, 3]]


def test_neighbour_search_rejects_bad_indices():
    state = make_state([0.0, 10.0], [0, 0])
    with pytest.raises(SafetyError, match="outside"):
        lane_leaders_followers(state, np.array([2]))
    with pytest.raises(SafetyError, match="1-D"):
        lane_leaders_followers(state, np.array([[0]]))


# ---------------------------------------------------------------- gap / TTC
def test_d_long_and_ttc_front_with_headings():
    th_i, th_j = 0.1, -0.2
    state = make_state(
        [100.0, 110.0], [1, 1], [20.0, 15.0], heading_rad=[th_i, th_j], length_m=[5.0, 4.0]
    )
    kin = pair_kinematics(state, np.array([0]), np.array([1]))
    d = (110.0 - 100.0 - 4.5) * math.cos(th_i) - 0.9 * abs(math.sin(th_i))  # L_veh = (5+4)/2
    dv = 20.0 * abs(math.cos(th_i)) - 15.0 * abs(math.cos(th_j))
    assert kin.d_long_m[0] == pytest.approx(d)  # 5.38267
    assert kin.dv_long_mps[0] == pytest.approx(dv)  # 5.19908
    assert kin.ttc_s[0] == pytest.approx(d / dv)  # 1.03531


def test_d_long_and_ttc_rear_vehicle_is_negative_gap_positive_ttc():
    th_i = 0.1
    state = make_state([100.0, 92.0], [1, 1], [20.0, 25.0], heading_rad=[th_i, 0.0])
    kin = pair_kinematics(state, np.array([0]), np.array([1]))
    gap = (100.0 - 92.0 - 5.0) * math.cos(th_i) - 0.9 * abs(math.sin(th_i))
    dv = 20.0 * math.cos(th_i) - 25.0
    assert kin.d_long_m[0] == pytest.approx(-gap)
    assert kin.ttc_s[0] == pytest.approx(-gap / dv)  # rear is faster: closing, > 0
    # a slower rear vehicle is not closing -> inf
    slow = make_state([100.0, 92.0], [1, 1], [20.0, 15.0])
    assert np.isinf(pair_kinematics(slow, np.array([0]), np.array([1])).ttc_s[0])


def test_ttc_not_closing_or_absent_is_inf_and_risk_false():
    state = make_state([100.0, 110.0], [1, 1], [20.0, 20.0])
    kin = pair_kinematics(state, np.array([0, 0]), np.array([1, -1]))
    assert np.isinf(kin.ttc_s).all()
    assert kin.valid.tolist() == [True, False]
    assert np.isnan(kin.d_long_m[1])
    assert kin.risk(100.0, 100.0).tolist() == [False, False]


# ---------------------------------------------------------------- PSAR: lane change
def test_lane_change_without_target_lane_vehicles_is_left_alone():
    # a close, closing leader in the ego lane does not matter: lines 17-27 skip lane changes
    res = run_psar([(106.0, 1, 15.0), (50.0, 0, 20.0)], LANE_LEFT)
    check(res, LANE_LEFT, RULE_NONE)
    res = run_psar([(106.0, 1, 15.0), (150.0, 2, 20.0)], LANE_RIGHT)
    check(res, LANE_RIGHT, RULE_NONE)


def test_cancel_lc_front_gap_below_d_lc_min():
    check(run_psar([(105.5, 2, 20.0)], LANE_LEFT), REMAIN, CANCEL_LC)  # gap 0.5 m
    check(run_psar([(107.0, 2, 25.0)], LANE_LEFT), LANE_LEFT, RULE_NONE)  # gap 2, opening


def test_cancel_lc_front_risk_safe():
    check(run_psar([(109.0, 2, 17.0)], LANE_LEFT), REMAIN, CANCEL_LC)  # gap 4, TTC 1.33


def test_decel_lc_front_risk_safe_att():
    # gap 4, dv 1 -> TTC 4: Risk(d_safe, ttc_att) only; b_lc = min(|dv|, b_max) = 1
    check(run_psar([(109.0, 2, 19.0)], LANE_LEFT), LANE_LEFT, DECEL_LC, decel=1.0)


def test_decel_lc_front_risk_att_safe():
    # gap 12, dv 8 -> TTC 1.5: Risk(d_att, ttc_safe); b_lc = min(8, 2) = 2
    check(run_psar([(117.0, 2, 12.0)], LANE_LEFT), LANE_LEFT, DECEL_LC, decel=2.0)
    # gap 12, dv 3 -> TTC 4: neither risk -> untouched
    check(run_psar([(117.0, 2, 17.0)], LANE_LEFT), LANE_LEFT, RULE_NONE)


def test_cancel_lc_rear_gap_below_d_lc_min_and_overlap():
    check(run_psar([(94.5, 0, 15.0)], LANE_RIGHT), REMAIN, CANCEL_LC)  # gap 0.5, slower
    check(run_psar([(98.0, 0, 15.0)], LANE_RIGHT), REMAIN, CANCEL_LC)  # alongside, overlap


def test_cancel_lc_rear_risk_safe():
    check(run_psar([(91.0, 2, 23.0)], LANE_LEFT), REMAIN, CANCEL_LC)  # gap 4, TTC 1.33
    check(run_psar([(91.0, 2, 17.0)], LANE_LEFT), LANE_LEFT, RULE_NONE)  # rear slower


def test_cancel_lc_rear_risk_only_when_decel_lc_applies():
    rear = (85.0, 2, 26.0)  # gap 10, rear closing at 6 m/s -> TTC 1.67: Risk(d_att, ttc_safe)
    check(run_psar([rear], LANE_LEFT), LANE_LEFT, RULE_NONE)  # b_lc == 0: keep
    res = run_psar([rear, (117.0, 2, 12.0)], LANE_LEFT)  # front triggers Decel-LC first
    check(res, REMAIN, CANCEL_LC, decel=0.0)


def test_cancel_lc_then_force_brake_reports_both():
    # target front too close -> cancel; own-lane leader at gap 6, closing -> Force-Brake
    res = run_psar([(105.5, 2, 20.0), (111.0, 1, 18.0)], LANE_LEFT)
    check(res, DECELERATE, FORCE_BRAKE, mask=RULE_BITS[CANCEL_LC] | RULE_BITS[FORCE_BRAKE])
    assert rule_counts(res.rule_mask).tolist() == [1, 0, 1, 0]


def test_lane_change_towards_missing_lane_becomes_remain():
    res = run_psar([(200.0, 1, 20.0)], LANE_RIGHT, ego_lane=0)
    check(res, REMAIN, RULE_NONE)
    assert res.invalid_lc.tolist() == [True]
    res = run_psar([(200.0, 2, 20.0)], LANE_LEFT, ego_lane=3)
    assert res.action.tolist() == [REMAIN] and res.invalid_lc.tolist() == [True]
    # lane 3 does not exist in the reduction segment (index 1) of train-25
    res = run_psar([], LANE_LEFT, ego_lane=2, segment=1)
    assert res.action.tolist() == [REMAIN] and res.invalid_lc.tolist() == [True]
    # ... and the car-following checks then apply to it
    res = run_psar([(111.0, 2, 18.0)], LANE_LEFT, ego_lane=2, segment=1)
    check(res, DECELERATE, FORCE_BRAKE)


# ---------------------------------------------------------------- PSAR: car following
def test_force_brake_gap_below_d_warn_and_closing():
    leader = (112.0, 1, 19.0)  # gap 7, closing
    check(run_psar([leader], REMAIN), DECELERATE, FORCE_BRAKE)
    check(run_psar([leader], ACCELERATE), DECELERATE, FORCE_BRAKE)
    check(run_psar([leader], DECELERATE), DECELERATE, RULE_NONE)  # already braking


def test_suppr_accel_gap_below_d_safe_or_d_warn_when_accelerating():
    near = (109.0, 1, 21.0)  # gap 4, opening
    check(run_psar([near], ACCELERATE), REMAIN, SUPPR_ACCEL)
    check(run_psar([near], REMAIN), REMAIN, RULE_NONE)
    check(run_psar([near], DECELERATE), REMAIN, SUPPR_ACCEL)  # literal Algorithm 1 line 21
    mid = (112.0, 1, 21.0)  # gap 7, opening
    check(run_psar([mid], ACCELERATE), REMAIN, SUPPR_ACCEL)
    check(run_psar([mid], DECELERATE), DECELERATE, RULE_NONE)


def test_force_brake_risk_att_warn():
    check(run_psar([(117.0, 1, 15.0)], REMAIN), DECELERATE, FORCE_BRAKE)  # gap 12, TTC 2.4
    check(run_psar([(126.0, 1, 15.0)], REMAIN), REMAIN, RULE_NONE)  # gap 21 > d_att


def test_suppr_accel_risk_att_att_only_for_accelerate():
    leader = (117.0, 1, 17.0)  # gap 12, TTC 4
    check(run_psar([leader], ACCELERATE), REMAIN, SUPPR_ACCEL)
    check(run_psar([leader], REMAIN), REMAIN, RULE_NONE)
    check(run_psar([(117.0, 1, 18.0)], ACCELERATE), ACCELERATE, RULE_NONE)  # TTC 6


def test_inactive_vehicles_are_ignored_and_inactive_cav_passes_through():
    res = run_psar([(109.0, 1, 15.0)], ACCELERATE, active=[True, False])
    check(res, ACCELERATE, RULE_NONE)
    res = run_psar([(109.0, 1, 15.0)], ACCELERATE, active=[False, True])
    check(res, ACCELERATE, RULE_NONE)
    assert res.active.tolist() == [False]


def test_psar_vectorised_matches_single_cav_runs():
    # three CAVs in separate lanes, each in a different situation
    x = [100.0, 112.0, 300.0, 309.0, 500.0 - 60, 400.0]
    lane = [1, 1, 2, 2, 0, 3]
    speed = [20.0, 19.0, 20.0, 21.0, 20.0, 20.0]
    cav = [True, False, True, False, True, True]
    state = make_state(x, lane, speed, is_cav=cav)
    cavs = np.array([0, 2, 4, 5])
    actions = np.array([REMAIN, ACCELERATE, LANE_RIGHT, LANE_LEFT])
    res = psar(state, cavs, actions, CFG, ROAD)
    assert res.action.tolist() == [DECELERATE, REMAIN, REMAIN, REMAIN]
    assert res.rule.tolist() == [FORCE_BRAKE, SUPPR_ACCEL, RULE_NONE, RULE_NONE]
    assert res.invalid_lc.tolist() == [False, False, True, True]
    for k in range(len(cavs)):
        one = psar(state, cavs[k : k + 1], actions[k : k + 1], CFG, ROAD)
        assert one.action[0] == res.action[k] and one.rule[0] == res.rule[k]


def test_psar_rejects_bad_input():
    state = make_state([0.0, 10.0], [0, 0], is_cav=[True, False])
    with pytest.raises(SafetyError, match="0..4"):
        psar(state, np.array([0]), np.array([5]), CFG, ROAD)
    with pytest.raises(SafetyError, match="shape"):
        psar(state, np.array([0]), np.array([0, 1]), CFG, ROAD)
    with pytest.raises(ConfigError, match="d_safe_m"):
        PSARConfig(d_safe_m=20.0)


# ---------------------------------------------------------------- events
def test_waiting_and_safety_critical_events():
    cfg = EventConfig()  # waiting < 3 m/s, gap < 1 m, TTC < 1.5 s, accel < -4.5
    #           0 slow  1 lead  2 close 3 lead  4 fast  5 lead  6 brake 7 off
    x = [10.0, 100.0, 200.0, 205.8, 300.0, 310.0, 400.0, 401.0]
    lane = [0, 0, 1, 1, 2, 2, 3, 3]
    speed = [2.0, 10.0, 10.0, 10.0, 20.0, 12.0, 10.0, 0.0]
    accel = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -5.0, 0.0]
    active = [True] * 7 + [False]
    state = make_state(x, lane, speed, accel_mps2=accel, active=active, collisions=[(1, 0)])
    assert waiting_events(state, cfg).tolist() == [True] + [False] * 7
    ev = safety_critical_events(state, cfg)
    assert ev.small_gap.tolist() == [False, False, True, False, False, False, False, False]
    # vehicle 4: gap 5, dv 8 -> TTC 0.625 s
    assert ev.low_ttc.tolist() == [False, False, False, False, True, False, False, False]
    assert ev.collision.tolist() == [True, True] + [False] * 6
    assert ev.emergency_brake.tolist() == [False] * 6 + [True, False]
    assert ev.any.tolist() == [True, True, True, False, True, False, True, False]


# ---------------------------------------------------------------- PSAR vs a scalar reference
def _reference_psar(state, i: int, a: int, cfg: PSARConfig) -> tuple[int, float]:
    """Algorithm 1 for one CAV, written line by line with Python scalars."""

    def neighbour(lane: int, front: bool) -> int:
        best, best_dist = -1, math.inf
        for j in range(state.n_vehicles):
            if j == i or not state.active[j] or state.lane[j] != lane:
                continue
            dx = state.x_m[j] - state.x_m[i]
            if (dx >= 0) == front and abs(dx) < best_dist:
                best, best_dist = j, abs(dx)
        return best

    def kin(j: int) -> tuple[float, float, float]:
        th_i = state.heading_rad[i]
        half = 0.5 * (state.length_m[i] + state.length_m[j])
        dx = state.x_m[j] - state.x_m[i]
        gap = (abs(dx) - half) * math.cos(th_i) - 0.5 * state.width_m[i] * abs(math.sin(th_i))
        d = gap if dx >= 0 else -gap
        dv = state.speed_mps[i] * abs(math.cos(th_i)) - state.speed_mps[j] * abs(
            math.cos(state.heading_rad[j])
        )
        ttc = d / dv if dv != 0 and d / dv > 0 else math.inf
        return d, dv, ttc

    def risk(d: float, ttc: float, d0: float, t0: float) -> bool:
        return abs(d) <= d0 and 0 < ttc <= t0

    lane = int(state.lane[i])
    if a in (LANE_LEFT, LANE_RIGHT):
        target = lane + (1 if a == LANE_LEFT else -1)
        exists = 0 <= target < ROAD.max_lanes and ROAD.lane_exists()[state.segment[i], target]
        if not exists:
            a = REMAIN
    b_lc = 0.0
    if a in (LANE_LEFT, LANE_RIGHT):
        target = lane + (1 if a == LANE_LEFT else -1)
        j = neighbour(target, front=True)
        if j >= 0:
            d, dv, ttc = kin(j)
            if d <= cfg.d_lc_min_m or risk(d, ttc, cfg.d_safe_m, cfg.ttc_safe_s):
                a = REMAIN
            elif risk(d, ttc, cfg.d_safe_m, cfg.ttc_att_s) or risk(
                d, ttc, cfg.d_att_m, cfg.ttc_safe_s
            ):
                b_lc = min(abs(dv), cfg.b_max_mps2)
        k = neighbour(target, front=False)
        if k >= 0 and a != REMAIN:
            d, dv, ttc = kin(k)
            if -d <= cfg.d_lc_min_m or risk(d, ttc, cfg.d_safe_m, cfg.ttc_safe_s):
                a = REMAIN
            elif (
                risk(d, ttc, cfg.d_safe_m, cfg.ttc_att_s)
                or risk(d, ttc, cfg.d_att_m, cfg.ttc_safe_s)
            ) and b_lc != 0:
                a = REMAIN
    if a in (REMAIN, ACCELERATE, DECELERATE):
        b_lc = 0.0
        j = neighbour(lane, front=True)
        if j >= 0:
            d, _, ttc = kin(j)
            if d <= cfg.d_warn_m and ttc < math.inf:
                a = DECELERATE
            elif d <= cfg.d_safe_m or (d <= cfg.d_warn_m and a == ACCELERATE):
                a = REMAIN
            elif risk(d, ttc, cfg.d_att_m, cfg.ttc_warn_s):
                a = DECELERATE
            elif risk(d, ttc, cfg.d_att_m, cfg.ttc_att_s) and a == ACCELERATE:
                a = REMAIN
    return a, b_lc


def test_psar_matches_scalar_reference_on_random_dense_traffic():
    rng = np.random.default_rng(7)
    fired = np.zeros(4, dtype=np.int64)
    for _ in range(150):
        n = int(rng.integers(2, 16))
        x = rng.uniform(0.0, 80.0, n)
        state = make_state(
            x,
            rng.integers(0, 4, n),
            rng.uniform(0.0, 25.0, n),
            is_cav=rng.random(n) < 0.5,
            heading_rad=rng.normal(0.0, 0.05, n),
            length_m=rng.uniform(4.0, 6.0, n),
            active=rng.random(n) < 0.9,
            segment=0,
        )
        cavs = np.flatnonzero(state.is_cav[0])
        actions = rng.integers(0, 5, cavs.shape[0])
        res = psar(state, cavs, actions, CFG, ROAD)
        fired += rule_counts(res.rule_mask)
        one = first_env(state)  # its (V,) rows, for the scalar reference
        for k, (i, a) in enumerate(zip(cavs, actions, strict=True)):
            if not one.active[i]:
                assert res.action[k] == a and res.rule[k] == RULE_NONE
                continue
            ref_a, ref_b = _reference_psar(one, int(i), int(a), CFG)
            assert res.action[k] == ref_a
            assert res.decel_lc_mps2[k] == pytest.approx(ref_b)
    assert (fired > 0).all()  # every rule was exercised


@pytest.mark.parametrize("horizon, seen", [("stopping", DECELERATE), ("headway", REMAIN)])
@pytest.mark.parametrize("other_lane, drift_m", [(2, -0.1), (0, +0.1)])
def test_a_vehicle_starting_to_cut_in_is_a_front_obstacle(other_lane, drift_m, horizon, seen):
    """The SUMO crash of the heuristic (issue 23): an HDV standing 17 m ahead in the next
    lane begins to move across; the CAV must not accelerate into its gap. "headway" lets
    it keep 7.3 m/s (7.3 m in the step + 6.7 m braking at 4 m/s2 + 2 m < 17 m)."""
    centre_m = ROAD.lane_center_y_m(np.array([1, other_lane]))
    x, lane, speed = [448.0, 470.0], [1, other_lane], [7.3, 0.0]
    for drift, expected in ((drift_m, seen), (0.0, ACCELERATE), (-drift_m, ACCELERATE)):
        y = [float(centre_m[0]), float(centre_m[1]) + drift]  # drift towards / none / away
        state = make_state(x, lane, speed, is_cav=[True, False], y_m=y)
        res = psar(state, np.array([0]), np.array([ACCELERATE]), PSARConfig(horizon=horizon), ROAD)
        assert res.action.tolist() == [expected], drift


def test_the_cut_in_behind_a_vehicle_alongside_is_seen():
    """The merging vehicle need not be the nearest one of its lane (test-50 crash)."""
    centre_m = ROAD.lane_center_y_m(np.array([1, 2, 2]))
    y = [float(centre_m[0]), float(centre_m[1]), float(centre_m[2]) - 0.1]
    state = make_state(
        [806.6, 810.0, 832.4], [1, 2, 2], [9.5, 9.0, 0.0], is_cav=[True, False, False], y_m=y
    )
    res = psar(state, np.array([0]), np.array([ACCELERATE]), PSARConfig(), ROAD)
    assert res.action.tolist() == [DECELERATE]
