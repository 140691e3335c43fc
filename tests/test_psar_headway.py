"""PSAR's ``"headway"`` horizon: human-like gaps behind HDVs, close ones behind known CAVs.

Every case has a gap that can be computed by hand from
:func:`diacc.sim.kinematics.safe_end_speed_mps` (see the comments): CAVs act
once per 1 s step, plan braking at 4 m/s^2, keep ``min_gap_m`` = 2 m and,
behind a CAV whose command is known, ``cav_time_gap_s`` = 0.3 s.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers import make_state, one_env

from diacc.config import ConfigError, PSARConfig, SimConfig
from diacc.envs.actions import ACCELERATE, DECELERATE, LANE_LEFT, LANE_RIGHT, REMAIN
from diacc.envs.psar import CANCEL_LC, FORCE_BRAKE, SUPPR_ACCEL, psar
from diacc.envs.psar.headway_bound import exit_room_m
from diacc.sim.kinematics import braking_step, safe_end_speed_mps, safe_gap_m
from diacc.sim.maps import load_map

# The tests below read one env: (C,) arrays in and out of an E = 1 batch.
psar = one_env(psar)

ROAD = load_map("train-25")
SIM = SimConfig()
HEADWAY = PSARConfig(horizon="headway")
STOPPING = PSARConfig(horizon="stopping")  # the default before 2026-12-02
LENGTH_M = 5.0  # make_state's vehicles: centre distance = bumper gap + 5 m


def run(x, lane, speed, is_cav, actions, cfg=HEADWAY):
    """PSAR for every CAV of a hand-built state (slots in vehicle order)."""
    state = make_state(x, lane, speed, is_cav=is_cav)
    cav_index = np.flatnonzero(np.asarray(is_cav))
    return psar(state, cav_index, np.asarray(actions), cfg, ROAD, SIM)


def test_unknown_leader_bound_is_gipps_with_one_step_of_reaction():
    distance_m, end_mps = braking_step(18.0, 1.0, 4.0)
    assert (distance_m, end_mps) == pytest.approx((16.0, 14.0))  # 18 -> 14 m/s in 1 s
    u = safe_end_speed_mps(30.0, 20.0, distance_m, end_mps, 1.0, 4.0, 2.0)
    assert 2.0 + safe_gap_m(20.0, 18.0, 1.0, 4.0, u) == pytest.approx(30.0)
    # Behind a known leader at 20 m/s holding its speed: 2 m + 0.3 s x 20 m/s = 8 m.
    assert safe_end_speed_mps(8.0, 20.0, 20.0, 20.0, 1.0, 4.0, 2.0, 0.3) == pytest.approx(20.0)


def root(a: float, b: float, c: float) -> float:
    """The positive root of a u^2 + b u - c = 0."""
    return (-b + math.sqrt(b * b + 4 * a * c)) / (2 * a)


def test_behind_an_hdv_one_second_plus_the_standstill_gap():
    # A normal HDV may brake at 4.5 m/s^2, the CAV answers with its full 5 m/s^2:
    # at equal speeds 20 m/s, remain needs 2 m + 20 m/s x 1 s = 22 m (1.1 s).
    res = run([100.0, 100.0 + LENGTH_M + 22.5], [1, 1], 20.0, [True, False], [REMAIN])
    assert res.rule.tolist() == [0] and res.speed_change_mps[0] == 0.0
    # Accelerating is cut to the safe end speed u:
    # u^2 / (2 x 4.5) + u / 2 = 22.5 - 2 - 20 / 2 + 20^2 / (2 x 4.5).
    res = run([100.0, 100.0 + LENGTH_M + 22.5], [1, 1], 20.0, [True, False], [ACCELERATE])
    assert res.rule.tolist() == [SUPPR_ACCEL] and res.action.tolist() == [REMAIN]
    u = root(1 / 9, 0.5, 10.5 + 400 / 9)
    assert res.speed_change_mps[0] == pytest.approx(u - 20.0) and 0 < u - 20 < 0.2
    # Half a metre short: brake a little, not by a whole action.
    res = run([100.0, 100.0 + LENGTH_M + 21.5], [1, 1], 20.0, [True, False], [REMAIN])
    assert res.rule.tolist() == [FORCE_BRAKE] and res.action.tolist() == [DECELERATE]
    assert res.speed_change_mps[0] == pytest.approx(root(1 / 9, 0.5, 9.5 + 400 / 9) - 20.0)
    # Behind an aggressive HDV (5.5 m/s^2) 22.5 m is too little:
    # u^2 / (2 x 5) + u / 2 = 22.5 - 2 - 20 / 2 + 20^2 / (2 x 5.5) gives u < 20.
    aggressive = make_state([100.0, 127.5], [1, 1], 20.0, is_cav=[True, False])
    aggressive.style[0, 1] = 0
    res = psar(aggressive, np.array([0]), np.array([REMAIN]), HEADWAY, ROAD, SIM)
    assert res.speed_change_mps[0] == pytest.approx(root(0.1, 0.5, 10.5 + 400 / 11) - 20.0)
    assert res.rule.tolist() == [FORCE_BRAKE]
    # The "stopping" horizon wants about twice the gap before it lets a CAV accelerate.
    stop = run([100.0, 127.5], [1, 1], 20.0, [True, False], [ACCELERATE], STOPPING)
    assert stop.action.tolist() == [REMAIN]


def test_full_brake_threat_restores_a_short_gap_at_the_planned_rate():
    # An HDV 10 m ahead, 5 m/s slower (it cut in): the headway bound asks for a
    # speed drop beyond the planned 4 m/s^2. "bound" brakes at the full 5 m/s^2 (an
    # emergency by the metrics' 4.5 threshold); "threat" brakes at the planned rate
    # and restores the gap over the next steps, unless the HDV brakes or is too close.
    x, lane, is_cav, speed = [100.0, 100.0 + LENGTH_M + 10.0], [1, 1], [True, False], [20.0, 15.0]
    threat = PSARConfig(horizon="headway", full_brake="threat")
    full = run(x, lane, speed, is_cav, [REMAIN], PSARConfig(horizon="headway", full_brake="bound"))
    assert full.rule.tolist() == [FORCE_BRAKE] and full.speed_change_mps[0] == -5.0
    planned = run(x, lane, speed, is_cav, [REMAIN], threat)
    assert planned.rule.tolist() == [FORCE_BRAKE] and planned.speed_change_mps[0] == -4.0
    braking = make_state(x, lane, speed, is_cav=is_cav, accel_mps2=[0.0, -4.5])
    res = psar(braking, np.array([0]), np.array([REMAIN]), threat, ROAD, SIM)
    assert res.speed_change_mps[0] == -5.0
    close = make_state([100.0, 100.0 + LENGTH_M + 1.5], lane, speed, is_cav=is_cav)
    res = psar(close, np.array([0]), np.array([REMAIN]), threat, ROAD, SIM)
    assert res.speed_change_mps[0] == -5.0
    with pytest.raises(ConfigError, match="full_brake"):
        PSARConfig(full_brake="sometimes")


def test_full_brake_known_judges_a_cav_leader_by_its_command():
    # A CAV 4 m behind a CAV leader at 20 / 18 m/s (it cut in): the bound behind the
    # known leader asks for more than the planned 4 m/s. "threat" counts every CAV
    # leader as a threat and brakes at the full 5 m/s^2; "known" sees the leader
    # hold its speed and planned braking keep min_gap_m: 4 m/s^2.
    x, lane, is_cav = [100.0, 100.0 + LENGTH_M + 4.0], [1, 1], [True, True]
    speed = [20.0, 18.0]
    threat = run(x, lane, speed, is_cav, [REMAIN, REMAIN], PSARConfig(full_brake="threat"))
    known_cfg = PSARConfig(full_brake="known")
    known = run(x, lane, speed, is_cav, [REMAIN, REMAIN], known_cfg)
    assert threat.speed_change_mps[0] == -5.0 and known.speed_change_mps[0] == -4.0
    assert known.rule.tolist() == [FORCE_BRAKE, 0]
    # The leader brakes harder than planned (a standing HDV 12 m ahead of it): a threat.
    x3, lane3 = [*x, x[1] + LENGTH_M + 12.0], [1, 1, 1]
    res = run(x3, lane3, [*speed, 0.0], [True, True, False], [REMAIN, REMAIN], known_cfg)
    assert res.speed_change_mps[1] == -5.0 and res.speed_change_mps[0] == -5.0
    # Closer than min_gap_m, or planned braking falls short behind the known motion.
    close = run([100.0, 100.0 + LENGTH_M + 1.5], lane, speed, is_cav, [REMAIN, REMAIN], known_cfg)
    assert close.speed_change_mps[0] == -5.0
    slow = run(x, lane, [20.0, 8.0], is_cav, [REMAIN, REMAIN], known_cfg)
    assert slow.speed_change_mps[0] == -5.0
    # The leader's slot is what makes it known: a CAV without one is judged as before.
    state = make_state(x, lane, speed, is_cav=is_cav)
    alone = psar(state, np.array([0]), np.array([REMAIN]), known_cfg, ROAD, SIM)
    assert alone.speed_change_mps[0] == -5.0


@pytest.mark.parametrize("full_brake", ["bound", "threat", "known"])
def test_a_cav_platoon_that_only_accelerates_stops_behind_a_standing_hdv(full_brake):
    # Closed loop: three CAVs 10 m apart ask to accelerate every step towards an HDV
    # standing 100 m ahead of the head; every rule must stop all three without contact.
    cfg = PSARConfig(horizon="headway", full_brake=full_brake)
    for speed_mps in (14.0, 22.0):
        x_m = np.array([100.0, 115.0, 130.0])
        v_mps, accel_mps2 = np.full(3, speed_mps), np.zeros(3)
        hdv_x_m = x_m[-1] + LENGTH_M + 100.0
        for _ in range(40):
            state = make_state(
                [*x_m, hdv_x_m],
                [1, 1, 1, 1],
                [*v_mps, 0.0],
                is_cav=[True, True, True, False],
                accel_mps2=[*accel_mps2, 0.0],
            )
            res = psar(state, np.arange(3), np.full(3, ACCELERATE), cfg, ROAD, SIM)
            end_mps = np.maximum(v_mps + res.speed_change_mps, 0.0)
            x_m = x_m + 0.5 * (v_mps + end_mps) * SIM.step_s
            accel_mps2, v_mps = (end_mps - v_mps) / SIM.step_s, end_mps
            gaps_m = np.diff([*x_m, hdv_x_m]) - LENGTH_M
            assert gaps_m.min() >= 1.0, (speed_mps, gaps_m)
        assert (v_mps == 0.0).all()


@pytest.mark.parametrize("full_brake", ["bound", "threat", "known"])
def test_a_cav_that_only_accelerates_stops_behind_a_standing_hdv(full_brake):
    # Closed loop: a CAV asking to accelerate every step drives up to an HDV
    # standing in its lane (the end of a jam, say). PSAR must stop it about
    # min_gap_m behind, from any approach, with either full-brake rule; a "threat"
    # rule that saw no threat in a standing HDV braked at the planned rate after
    # the bound had planned a full brake, and hit it (learning evidence, train-50
    # seed 2001644268; here from 25 m/s and 150 m).
    cfg = PSARConfig(horizon="headway", full_brake=full_brake)
    for speed_mps in (8.0, 14.0, 20.0, 25.0):
        for gap_m in (80.0, 100.0, 120.0, 150.0):  # far enough to stop from any of them
            x_m, v_mps, accel_mps2 = 100.0, speed_mps, 0.0
            hdv_x_m = x_m + LENGTH_M + gap_m
            for _ in range(40):
                state = make_state(
                    [x_m, hdv_x_m],
                    [1, 1],
                    [v_mps, 0.0],
                    is_cav=[True, False],
                    accel_mps2=[accel_mps2, 0.0],
                )
                res = psar(state, np.array([0]), np.array([ACCELERATE]), cfg, ROAD, SIM)
                end_mps = max(v_mps + float(res.speed_change_mps[0]), 0.0)
                x_m += 0.5 * (v_mps + end_mps) * SIM.step_s  # commands ramp over the step
                accel_mps2, v_mps = (end_mps - v_mps) / SIM.step_s, end_mps
                # min_gap_m less the crawl of the last steps (1.44 m at least, measured)
                assert hdv_x_m - x_m - LENGTH_M >= 1.0, (speed_mps, gap_m)
            assert v_mps == 0.0


def test_platoon_follows_a_known_leader_closely_front_to_back():
    # Slots listed back to front on purpose: PSAR must still decide the leader first.
    x = [100.0, 100.0 + 1 * (LENGTH_M + 8.0), 100.0 + 2 * (LENGTH_M + 8.0)]
    res = run(x, [1, 1, 1], 20.0, [True, True, True], [REMAIN, REMAIN, REMAIN])
    assert res.rule.tolist() == [0, 0, 0]  # 8 m = 2 m + 0.3 s x 20 m/s is enough
    # Behind an HDV the same 8 m would force braking.
    res = run(x[1:], [1, 1], 20.0, [True, False], [REMAIN])
    assert res.rule.tolist() == [FORCE_BRAKE]
    # The head brakes by one action (20 -> 18 m/s over 19 m); its follower brakes
    # to u with u^2 / 8 + 0.8u = 8 + 19 - 10 - 2 + 18^2 / 8; the last one brakes for that.
    res = run(x, [1, 1, 1], 20.0, [True, True, True], [REMAIN, REMAIN, DECELERATE])
    middle_mps = -3.2 + math.sqrt(3.2**2 + 444.0)
    assert res.speed_change_mps[2] == pytest.approx(-2.0)
    assert res.speed_change_mps[1] == pytest.approx(middle_mps - 20.0)
    assert res.rule.tolist() == [FORCE_BRAKE, FORCE_BRAKE, 0]
    middle_step_m = 0.5 * (20.0 + middle_mps)
    behind_mps = safe_end_speed_mps(8.0, 20.0, middle_step_m, middle_mps, 1.0, 4.0, 2.0, 0.3)
    assert res.speed_change_mps[0] == pytest.approx(behind_mps - 20.0)
    assert 0.0 > res.speed_change_mps[0] > -4.0  # within the planned braking


def test_lane_change_in_front_of_a_cav_leaves_no_wide_hole():
    # CAV 0 moves into lane 2 between an HDV 23 m ahead and a CAV 9 m behind (20 m/s).
    # Front: 1 m + (2 - 1) m + Gipps 20 m = 22 m; rear CAV: 1 m + 0.3 s x 20 m/s = 7 m.
    x = [100.0, 100.0 + LENGTH_M + 23.0, 100.0 - LENGTH_M - 9.0]
    lanes, cavs = [1, 2, 2], [True, False, True]
    res = run(x, lanes, 20.0, cavs, [LANE_LEFT, ACCELERATE])
    assert res.action.tolist() == [LANE_LEFT, REMAIN]  # the rear CAV makes room at once
    assert res.rule.tolist() == [0, SUPPR_ACCEL]
    # The "stopping" horizon keeps a rear CAV one reacting, accelerating step away.
    res = run(x, lanes, 20.0, cavs, [LANE_LEFT, ACCELERATE], STOPPING)
    assert res.rule.tolist()[0] == CANCEL_LC
    # Too close to the front HDV: cancelled under "headway" as well.
    x_close = [100.0, 100.0 + LENGTH_M + 21.0, 100.0 - LENGTH_M - 9.0]
    assert run(x_close, lanes, 20.0, cavs, [LANE_LEFT, REMAIN]).rule.tolist()[0] == CANCEL_LC


def test_cavs_open_a_gap_for_a_cav_that_asks_to_merge():
    # CAV 0 (lane 2) asks for lane 1, where CAV 1 drives 3 m behind it: too close
    # (1 m + 0.3 s x 20 m/s = 7 m), so the change waits and CAV 1 brakes to open the gap.
    x, lanes = [100.0, 100.0 - LENGTH_M - 3.0], [2, 1]
    res = run(x, lanes, 20.0, [True, True], [LANE_RIGHT, ACCELERATE])
    assert res.rule.tolist() == [CANCEL_LC, FORCE_BRAKE]
    # Without cooperative merging CAV 1 drives on (it has no leader).
    selfish = PSARConfig(horizon="headway", cooperative_merge=False)
    res = run(x, lanes, 20.0, [True, True], [LANE_RIGHT, ACCELERATE], selfish)
    assert res.rule.tolist() == [CANCEL_LC, 0]
    # Alongside (less than d_LC,min behind its rear), CAV 1 passes instead of braking.
    res = run([100.0, 100.0 - LENGTH_M], lanes, 20.0, [True, True], [LANE_RIGHT, ACCELERATE])
    assert res.rule.tolist()[1] == 0


def test_a_cav_brakes_for_a_standing_cav_moving_in_behind_a_nearer_one_that_only_asks():
    # Learning evidence, highway train-50, sampled actions, episode seed 1637607931,
    # step 28: CAV A stands in lane 2 and moves right into lane 1, 18 m ahead of CAV B
    # (10 m/s); the rear check lets it, as B can brake at once (1 m + 0.3 s x 10 m/s +
    # 10^2 / 8 = 16.5 m). CAV C, 1 m behind A in lane 0 at 22 m/s, asks for lane 1 too
    # and is cancelled (A goes first). B used to follow only the nearest CAV entering
    # its lane, C, which drives on at 22 m/s, held 10 m/s and hit A two steps later.
    x = [300.0, 299.0, 300.0 - LENGTH_M - 18.0]  # A, C, B
    res = run(x, [2, 0, 1], [0.0, 22.0, 10.0], [True, True, True], [LANE_RIGHT, LANE_LEFT, REMAIN])
    assert res.action.tolist() == [LANE_RIGHT, REMAIN, DECELERATE]
    assert res.rule.tolist() == [0, CANCEL_LC, FORCE_BRAKE]
    # B brakes to u behind the standing A, u^2 / 8 + 0.8 u = 18 - 10 / 2 - 2, from
    # where it stops 2 m + 0.3 s x u behind A; within the planned 4 m/s^2.
    assert res.speed_change_mps[2] == pytest.approx(root(1 / 8, 0.8, 11.0) - 10.0)
    assert -4.0 < res.speed_change_mps[2] < -3.0


def test_outer_lane_of_a_double_drop_is_left_before_its_end():
    # train-50: lanes 2 and 3 end at 500 m. Lane 3 can only be left into lane 2, which
    # a standing car may enter only if lane 2 lasts its length beyond its centre, so
    # lane 3's wall moves back by 2.5 + 0.5 m; lane 2 (lane 1 survives) keeps its end.
    road = load_map("train-50")
    state = make_state([400.0, 400.0], [3, 2], 10.0, is_cav=True)
    assert exit_room_m(state, np.array([0, 1]), road).tolist() == pytest.approx([3.0, 0.0])


def test_a_standing_cav_at_a_lane_end_may_still_leave_it():
    # Lane 3 ends at 500 m; a CAV stands at its end and changes to lane 2 (free).
    res = run([497.5], [3], 0.0, [True], [LANE_RIGHT])
    assert res.action.tolist() == [LANE_RIGHT] and res.rule.tolist() == [0]


@pytest.mark.parametrize("gap_m", [*np.arange(-6.0, 12.0, 0.25), 1.0, 1.0 + 1e-9, 2.0])
def test_of_a_cav_waiting_at_a_lane_end_and_a_standing_cav_beside_it_one_moves(gap_m):
    # The zipper's liveness (issue 44): CAV 0 stands at the end of lane 2 (train-50, ends
    # at 500 m) and asks for lane 1, where CAV 1 stands with its front gap_m behind CAV
    # 0's rear (< 0: alongside) and asks to accelerate. Either CAV 0 changes (CAV 1 is
    # more than d_LC,min = 1 m behind and yields, or has room to move up behind it) or
    # CAV 1 drives on (alongside or closer, it lets CAV 0 in behind it); never both
    # wait. At exactly 1 m both used to.
    road = load_map("train-50")
    x_m = 500.0 - 0.5 * LENGTH_M - 1.0
    state = make_state([x_m, x_m - LENGTH_M - gap_m], [2, 1], 0.0, is_cav=True)
    res = psar(state, np.array([0, 1]), np.array([LANE_RIGHT, ACCELERATE]), HEADWAY, road, SIM)
    changes, drives_on = res.action[0] == LANE_RIGHT, res.speed_change_mps[1] > 0.0
    assert changes or drives_on
    assert changes == (gap_m > HEADWAY.d_lc_min_m)
    assert drives_on or gap_m <= HEADWAY.min_gap_m  # a yielding CAV closes up to 2 m


def test_unknown_horizon_is_a_one_line_error():
    with pytest.raises(ConfigError, match="'horizon' must be one of") as err:
        PSARConfig(horizon="tight")
    assert "\n" not in str(err.value) and "headway" in str(err.value)
    with pytest.raises(ConfigError, match="cav_time_gap_s"):
        PSARConfig(cav_time_gap_s=-0.1)


def test_a_batch_of_states_is_refined_as_each_state_alone():
    from dataclasses import fields

    from diacc.sim.backends.base import CavCommands
    from diacc.sim.backends.highway.backend import HighwayBackend
    from diacc.sim.scenario import Scenario
    from diacc.sim.state import TrafficState

    road = load_map("train-50")
    backend = HighwayBackend(road, SIM, n_envs=3)
    from diacc.envs.psar import psar as psar_of_batch

    states = [backend.reset(Scenario.with_cavs(25, 10), 7 + e, env=e).env(0) for e in range(3)]
    cav_index = np.stack([np.flatnonzero(s.is_cav[0]) for s in states])  # (E, C)
    rng = np.random.default_rng(5)
    for _ in range(8):
        actions = rng.integers(0, 5, cav_index.shape)
        batch = psar_of_batch(TrafficState.concat(states), cav_index, actions, HEADWAY, road, SIM)
        for e, state in enumerate(states):
            single = psar(state, cav_index[e], actions[e], HEADWAY, road, SIM)
            for f in fields(single):
                assert np.array_equal(getattr(single, f.name), getattr(batch, f.name)[e]), f.name
        speed = np.zeros((3, 25))
        np.put_along_axis(speed, cav_index, batch.speed_change_mps, axis=-1)
        stepped = backend.step(CavCommands(np.zeros((3, 25), np.int8), speed))
        states = [stepped.env(e) for e in range(3)]


def test_every_psar_option_value_has_its_rule_block():
    """HORIZONS and FORCE_BRAKES, the one place each option picks its block, cover every
    value PSARConfig accepts (a new value without a block would be a KeyError mid-step)."""
    from diacc.config import FORCE_BRAKE_MODES, HORIZON_MODES
    from diacc.envs.psar.car_following import FORCE_BRAKES
    from diacc.envs.psar.horizons import HORIZONS

    assert set(HORIZONS) == set(HORIZON_MODES)
    assert set(FORCE_BRAKES) == set(FORCE_BRAKE_MODES)
