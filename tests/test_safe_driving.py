"""Collision-free driving is possible: PSAR's physical options, lane ends, HDVs and CAVs.

The literal Algorithm 1 is tested line by line in ``test_safety.py``; this
file tests what the default options add (see :func:`diacc.envs.psar.psar`) and
that both simulators treat CAVs the way PSAR assumes.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import make_state, one_env

from diacc.config import PSARConfig, SimConfig
from diacc.envs.actions import ACCELERATE, DECELERATE, LANE_LEFT, LANE_RIGHT, REMAIN
from diacc.envs.psar import CANCEL_LC, FORCE_BRAKE, psar
from diacc.sim.backends.base import CavCommands, make_backend
from diacc.sim.kinematics import braking_step, safe_gap_m
from diacc.sim.maps import load_map
from diacc.sim.scenario import Scenario

# The tests below read one env: (C,) arrays in and out of an E = 1 batch.
psar = one_env(psar)

ROAD = load_map("train-25")  # lane 3 ends at 500 m
SIM = SimConfig()  # CAV safe braking 4 m/s2, actions +-2 m/s per 1 s step
DEFAULT = PSARConfig()  # the "headway" horizon since 2026-12-02
STOPPING = PSARConfig(horizon="stopping")  # the default before
LITERAL = PSARConfig(force_brake="paper", horizon="paper", coordinate_lane_changes=False)


def one_cav(others, action, cfg=DEFAULT, ego=(100.0, 1, 20.0), **kw):
    """PSAR for CAV 0 at ego = (x, lane, speed) among (x, lane, speed) HDVs."""
    x = [ego[0]] + [o[0] for o in others]
    lane = [ego[1]] + [o[1] for o in others]
    speed = [ego[2]] + [o[2] for o in others]
    state = make_state(x, lane, speed, is_cav=[True] + [False] * len(others), **kw)
    return psar(state, np.array([0]), np.array([action]), cfg, ROAD, SIM)


def test_safe_gap_is_gipps():
    assert safe_gap_m(25.0, 0.0, 1.0, 5.0) == pytest.approx(25.0 + 62.5)  # standing obstacle
    assert safe_gap_m(20.0, 20.0, 1.0, 4.0) == pytest.approx(20.0)  # reaction distance only
    assert safe_gap_m(10.0, 20.0, 0.0, 4.0) == 0.0  # leader faster, no reaction: no need
    # accelerating to 12 m/s during the reaction step, then braking at 4 m/s2
    assert safe_gap_m(10.0, 10.0, 1.0, 4.0, 12.0) == pytest.approx(11.0 + (144 - 100) / 8)


def test_force_brake_cancels_the_closing_speed_within_the_braking_limit():
    leader = [(112.0, 1, 17.0)]  # gap 7 m, closing 3 m/s
    res = one_cav(leader, REMAIN, cfg=STOPPING)
    assert res.action.tolist() == [DECELERATE] and res.rule.tolist() == [FORCE_BRAKE]
    assert res.speed_change_mps.tolist() == pytest.approx([-4.0])  # min(3 + 2, 4 m/s per step)
    res = one_cav(leader, REMAIN, cfg=LITERAL)  # the literal reading: one action step
    assert res.speed_change_mps.tolist() == pytest.approx([-2.0])
    # "headway" sizes the braking by physics: at the planned 4 m/s2 while the HDV ahead
    # does not brake hard (full_brake="threat"), up to the CAV's physical limit (5 m/s2)
    # once it does, or always with full_brake="bound".
    res = one_cav(leader, REMAIN)
    assert res.action.tolist() == [DECELERATE] and res.rule.tolist() == [FORCE_BRAKE]
    assert res.speed_change_mps.tolist() == pytest.approx([-SIM.cav.safe_decel_mps2 * SIM.step_s])
    full = [-SIM.cav.decel_mps2 * SIM.step_s]
    assert one_cav(leader, REMAIN, accel_mps2=[0.0, -4.5]).speed_change_mps.tolist() == full
    bound = PSARConfig(full_brake="bound")
    assert one_cav(leader, REMAIN, cfg=bound).speed_change_mps.tolist() == pytest.approx(full)
    # A proposal that already brakes as hard is left alone only in the literal reading.
    assert one_cav(leader, DECELERATE, cfg=STOPPING).rule.tolist() == [FORCE_BRAKE]
    assert one_cav(leader, DECELERATE).rule.tolist() == [FORCE_BRAKE]
    assert one_cav(leader, DECELERATE, cfg=LITERAL).rule.tolist() == [0]


def test_stopping_horizon_sees_a_standing_queue_early_enough():
    queue = [(160.0, 1, 0.0)]  # 55 m ahead, standing; the CAV drives 25 m/s
    assert one_cav(queue, REMAIN, cfg=LITERAL).rule.tolist() == [0]  # beyond d_att = 15 m
    res = one_cav(queue, REMAIN, cfg=STOPPING, ego=(100.0, 1, 25.0))
    assert res.rule.tolist() == [FORCE_BRAKE] and res.speed_change_mps[0] == pytest.approx(-4.0)
    # Following at equal speed, one second of headway is needed to accelerate.
    assert one_cav([(130.0, 1, 20.0)], ACCELERATE, cfg=STOPPING).action.tolist() == [REMAIN]
    assert one_cav([(160.0, 1, 20.0)], ACCELERATE, cfg=STOPPING).action.tolist() == [ACCELERATE]


def test_a_gap_too_short_to_answer_a_braking_leader_is_opened_even_when_not_closing():
    # bench --safety, highway test-50, paper-congestion, episode 4: a CAV changed in
    # 10 m behind a faster CAV, which then braked; the follower held 12.3 m at
    # 20.6 m/s (leader 21 m/s), needed about 1 m + 18.7 m, and only "remained".
    leader = [(100.0 + 5.0 + 12.33, 1, 21.0)]
    res = one_cav(leader, REMAIN, ego=(100.0, 1, 20.63))
    assert res.action.tolist() == [DECELERATE] and res.rule.tolist() == [FORCE_BRAKE]
    assert one_cav(leader, REMAIN, ego=(100.0, 1, 20.63), cfg=LITERAL).rule.tolist() == [0]
    # Played out: the leader brakes at the planned 4 m/s2 from now on, the CAV does
    # what PSAR says each 1 s step; it must stop behind the leader without contact.
    follower_x_m, follower_mps, leader_x_m, leader_mps = 100.0, 20.63, *leader[0][::2]
    for _ in range(12):
        res = one_cav([(leader_x_m, 1, leader_mps)], REMAIN, ego=(follower_x_m, 1, follower_mps))
        step_m, leader_mps = braking_step(leader_mps, 1.0, 4.0)
        leader_x_m += float(step_m)
        end_mps = max(follower_mps + float(res.speed_change_mps[0]), 0.0)
        if end_mps < follower_mps:  # braking: stops within the step if it must
            step_m, end_mps = braking_step(follower_mps, 1.0, follower_mps - end_mps)
        else:
            step_m = 0.5 * (follower_mps + end_mps)
        follower_x_m, follower_mps = follower_x_m + float(step_m), float(end_mps)
        assert leader_x_m - follower_x_m - 5.0 > 0.0
    assert follower_mps == 0.0 and float(leader_mps) == 0.0
    # Not for a standing CAV, nor with room to answer.
    assert one_cav([(105.5, 1, 0.0)], REMAIN, ego=(100.0, 1, 0.0)).rule.tolist() == [0]
    assert one_cav([(130.0, 1, 20.0)], REMAIN).rule.tolist() == [0]


@pytest.mark.parametrize("cfg", [DEFAULT, STOPPING], ids=lambda c: c.horizon)
def test_lane_end_is_a_wall_with_its_queue(cfg):
    # Lane 3 ends at 500 m: a CAV 60 m before it at 20 m/s must start braking.
    res = one_cav([], REMAIN, cfg=cfg, ego=(437.5, 3, 20.0))
    assert res.rule.tolist() == [FORCE_BRAKE]
    # Far from the end nothing happens.
    assert one_cav([], REMAIN, cfg=cfg, ego=(400.0, 3, 10.0)).rule.tolist() == [0]
    # A leader still rolling towards the end will queue there: the wall moves back by it.
    # "stopping" wants Gipps' gap (reaction step + braking) from 460 m at 10 m/s; "headway"
    # from 467 m needs 10 m (the step) + 12.5 m (braking) + 2 m to the wall, 23.5 m with
    # the leader's 5 m + 2 m queued in front of it, 30.5 m without.
    ego = (460.0, 3, 10.0) if cfg.horizon == "stopping" else (467.0, 3, 10.0)
    assert one_cav([], REMAIN, cfg=cfg, ego=ego).rule.tolist() == [0]
    leader = [(480.0, 3, 10.0)] if cfg.horizon == "stopping" else [(490.0, 3, 10.0)]
    assert one_cav(leader, REMAIN, cfg=cfg, ego=ego).rule.tolist() == [FORCE_BRAKE]


def test_lane_change_into_a_lane_ending_within_reach_is_not_made():
    res = one_cav([], LANE_LEFT, ego=(480.0, 2, 20.0))  # lane 3 ends 20 m ahead
    assert res.invalid_lc.tolist() == [True] and res.action.tolist() == [REMAIN]
    # The car-following checks still run for the replaced action.
    res = one_cav([(486.0, 2, 10.0)], LANE_LEFT, ego=(480.0, 2, 20.0))
    assert res.action.tolist() == [DECELERATE] and res.rule.tolist() == [FORCE_BRAKE]


def test_connected_cavs_do_not_change_into_each_other():
    # CAV 0 (lane 0) and CAV 1 (lane 2) both head for lane 1 side by side.
    state = make_state([100.0, 104.0], [0, 2], 15.0, is_cav=True)
    res = psar(state, np.array([0, 1]), np.array([LANE_LEFT, LANE_RIGHT]), DEFAULT, ROAD, SIM)
    assert res.action.tolist() == [REMAIN, LANE_RIGHT]  # the rear one yields
    assert res.rule.tolist()[0] == CANCEL_LC
    off = PSARConfig(coordinate_lane_changes=False)
    res = psar(state, np.array([0, 1]), np.array([LANE_LEFT, LANE_RIGHT]), off, ROAD, SIM)
    assert res.action.tolist() == [LANE_LEFT, LANE_RIGHT]


@pytest.mark.parametrize("backend_name", ["highway", "sumo"])
def test_cav_stops_at_the_end_of_its_lane_and_can_change_later(backend_name):
    """No simulator moves a CAV: in an ending lane it stops with its front at the end."""
    road = load_map("train-50")  # lanes 2 and 3 end at 500 m
    backend = make_backend(backend_name, road, SIM)
    try:
        for seed in range(20):
            state = backend.reset(Scenario(n_vehicles=1, cav_penetration=1.0), seed).env(0)
            cav = int(np.flatnonzero(state.is_cav)[0])
            if state.lane[cav] == 2:
                break
        assert state.lane[cav] == 2
        cmd = CavCommands.idle(1)
        for _ in range(40):
            cmd.speed_change_mps[0, cav] = 2.0
            state = backend.step(cmd).env(0)
            if state.speed_mps[cav] == 0.0 and state.x_m[cav] > 400:
                break
        assert state.lane[cav] == 2 and state.speed_mps[cav] == 0.0
        assert state.x_m[cav] + 0.5 * state.length_m[cav] == pytest.approx(500.0, abs=0.1)
        cmd.speed_change_mps[0, cav], cmd.lane_change[0, cav] = 0.0, -1
        state = backend.step(cmd).env(0)  # from standstill, within the step
        assert state.lane[cav] == 1
        assert state.y_m[cav] == pytest.approx(road.lane_center_y_m(1), abs=0.05)
    finally:
        backend.close()


@pytest.mark.parametrize("backend_name", ["highway", "sumo"])
def test_safety_benchmark_small(backend_name):
    """CI-sized ``diacc bench --safety``: PSAR keeps scripted CAVs collision-free."""
    from diacc.experiments.bench.safety import run

    rows = run(backends=(backend_name,), maps=("train-50",), policies=("accelerate",), episodes=2)
    (row,) = rows
    assert row.collision_free == 1.0 and row.hdv_hdv_collisions == 0
    assert row.arrived_fraction > 0.5  # and they do cross the bottleneck


@pytest.mark.parametrize("backend_name", ["highway", "sumo"])
def test_safety_benchmark_heuristic_congested(backend_name, capsys):
    """The heuristic under PSAR in the congested preset (the bench's second setting)."""
    from diacc.experiments.bench.safety import run

    rows = run(
        backends=(backend_name,),
        maps=("train-50",),
        policies=("heuristic",),
        episodes=1,
        style_preset="paper-congestion",
        episode_steps=120,
    )
    (row,) = rows
    assert row.meets_target and row.arrived_fraction > 0.5
    assert "style preset paper-congestion, 120-step episodes" in capsys.readouterr().out


def test_bench_safety_bad_episode_steps_is_one_line(capsys):
    from diacc.cli import main

    assert main(["bench", "--safety", "--episode-steps", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "diacc: error: --episode-steps must be in [1, 10000], got 0"
