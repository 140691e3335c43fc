"""The highway backend on real highway-env geometry: driver models, CAV commands, episodes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers import first_env

from diacc.config import AGGRESSIVE, CAUTIOUS, STYLE_PRESETS, SimConfig
from diacc.sim.backends.base import Backend, CavCommands
from diacc.sim.backends.highway.backend import HighwayBackend
from diacc.sim.backends.highway.dynamics import refresh_road_facts, refresh_speed_bounds
from diacc.sim.backends.highway.lanes import decide_lane_changes
from diacc.sim.maps import load_map
from diacc.sim.scenario import Scenario
from diacc.sim.state import validate_state
from diacc.sim.viewer import Viewer

SIM = SimConfig()


def make(map_name: str = "train-25") -> HighwayBackend:
    return HighwayBackend(load_map(map_name), SIM)


def run_hdv_episode(map_name: str, n: int, seed: int, max_steps: int = 200):
    """Pure-HDV episode until all arrived; returns (backend, states)."""
    backend = make(map_name)
    states = [first_env(backend.reset(Scenario.with_cavs(n, 0), seed))]
    for _ in range(max_steps):
        states.append(first_env(backend.step(CavCommands.idle(n))))
        if not states[-1].active.any():
            break
    return backend, states


def single_lane_backend(n: int, x_m: list[float], speed_mps: list[float], styles=None):
    """A backend whose vehicles are placed by hand in lane 0 (after a normal reset).

    Discretionary lane changes are switched off so that car following is tested alone.
    """
    return placed_backend("train-25", x_m, speed_mps, [0] * n, min_lane_change_speed_mps=1e9)


def placed_backend(map_name: str, x_m: list, speed_mps: list, lanes: list, **model):
    """A backend whose human drivers are placed by hand (after a normal reset), with
    ``model`` replacing fields of its :class:`HighwayModel`."""
    backend = make(map_name)
    backend.model = dataclasses.replace(backend.model, **model)
    backend.reset(Scenario.with_cavs(len(x_m), 0), 0)
    # The backend's arrays are (E, V) with E = 1 environment.
    backend.state.x_m = np.array([x_m], dtype=float)
    backend.state.speed_mps = np.array([speed_mps], dtype=float)
    backend.state.lane_from = np.array([lanes], dtype=np.intp)
    backend.state.lane_to = np.array([lanes], dtype=np.intp)
    backend.state.y_m = backend.road.lane_center_y_m(backend.state.lane_from).astype(float)
    backend.caches.leaders_dirty[:] = True
    refresh_road_facts(backend, np.ones(1, bool))
    refresh_speed_bounds(backend)
    return backend


def test_protocol_and_state_valid():
    backend = make()
    assert isinstance(backend, Backend) and backend.name == "highway"
    state = backend.reset(Scenario(), 3)
    validate_state(state)
    assert state.is_cav.sum() == 10 and state.collisions.shape == (0, 3)
    state = backend.step(CavCommands.idle(25))
    validate_state(state)
    assert state.step.tolist() == [1] and state.time_s == pytest.approx([SIM.step_s])


def test_idm_free_road_reaches_desired_speed():
    backend = single_lane_backend(1, [10.0], [5.0])
    for _ in range(40):
        state = first_env(backend.step(CavCommands.idle(1)))
    assert state.speed_mps[0] == pytest.approx(25.0, abs=0.6)


@pytest.mark.parametrize("style", [AGGRESSIVE, CAUTIOUS])
def test_follower_keeps_min_gap_behind_stopping_leader(style):
    # The leader is a wreck standing still; the follower must stop behind it.
    backend = single_lane_backend(2, [120.0, 20.0], [0.0, 25.0])
    backend.params.style[:] = style
    preset = STYLE_PRESETS[SIM.style_preset][style]
    backend.params.idm.min_gap_m[:] = preset.min_gap_m
    backend.params.idm.headway_s[:] = preset.time_headway_s
    backend.state.crashed[0, 0] = True
    refresh_speed_bounds(backend)
    backend.caches.leaders_dirty[:] = True
    gaps = []
    for _ in range(30):
        s = first_env(backend.step(CavCommands.idle(2)))
        gaps.append(s.x_m[0] - s.x_m[1] - SIM.vehicle_length_m)
    assert min(gaps) >= preset.min_gap_m - 1e-6
    assert s.speed_mps[1] < 0.1 and len(s.collisions) == 0


def _steady_headway(style: int) -> float:
    backend = single_lane_backend(2, [60.0, 10.0], [15.0, 15.0])
    preset = STYLE_PRESETS[SIM.style_preset][style]
    for arr, val in (
        (backend.params.idm.headway_s, preset.time_headway_s),
        (backend.params.idm.min_gap_m, preset.min_gap_m),
        (backend.params.idm.accel_mps2, preset.accel_mps2),
        (backend.params.idm.decel_mps2, preset.decel_mps2),
    ):
        arr[0, 1] = val
    backend.params.inv_2_sqrt_ab_s2_per_m = 0.5 / np.sqrt(
        backend.params.idm.accel_mps2 * backend.params.idm.decel_mps2
    )
    # Leader: a CAV-like constant 15 m/s (hold the speed window fixed).
    backend.state.is_cav[0, 0] = True
    backend.state.cav_accel_mps2[0, 0] = 0.0
    backend.state.cav_target_mps[0, 0] = 15.0
    refresh_speed_bounds(backend)
    for _ in range(40):
        s = first_env(backend.step(CavCommands.idle(2)))
    return (s.x_m[0] - s.x_m[1] - SIM.vehicle_length_m) / s.speed_mps[1]


def test_aggressive_headway_shorter_than_cautious():
    assert _steady_headway(AGGRESSIVE) < _steady_headway(CAUTIOUS) - 0.2


@pytest.mark.parametrize("map_name", ["train-25", "train-50", "test-25", "test-50"])
@pytest.mark.parametrize("n", [25, 40])
def test_pure_hdv_everyone_arrives_without_collisions(map_name, n):
    seeds = range(3) if n == 40 else range(10)
    for seed in seeds:
        backend, states = run_hdv_episode(map_name, n, seed)
        final = states[-1]
        assert final.arrived.all(), f"{map_name} N={n} seed={seed}: not all arrived"
        assert sum(len(s.collisions) for s in states) == 0
        assert backend.stats["guard_events"] == 0
        # Every vehicle went through the bottleneck segment (index 1).
        assert final.arrived.sum() == n


def test_same_seed_same_trajectory_different_seed_differs():
    _, a = run_hdv_episode("train-50", 25, 7, max_steps=40)
    _, b = run_hdv_episode("train-50", 25, 7, max_steps=40)
    _, c = run_hdv_episode("train-50", 25, 8, max_steps=40)
    xa, xb, xc = (np.stack([s.x_m for s in r]) for r in (a, b, c))
    assert np.array_equal(xa, xb)
    assert not np.array_equal(xa, xc)


def _cav_backend():
    backend = make()
    state = first_env(backend.reset(Scenario.with_cavs(25, 10), 0))
    return backend, state


def test_cav_lane_change_completes_within_step():
    backend, state = _cav_backend()
    cav = int(np.flatnonzero(state.is_cav & (state.lane < 3))[0])
    cmd = CavCommands.idle(25)
    cmd.lane_change[0, cav] = 1
    after = first_env(backend.step(cmd))
    assert after.lane[cav] == state.lane[cav] + 1
    assert after.y_m[cav] == pytest.approx(backend.road.lane_center_y_m(state.lane[cav] + 1))


def test_cav_lane_change_towards_missing_lane_ignored():
    backend, state = _cav_backend()
    cav = int(np.flatnonzero(state.is_cav & (state.lane == 0))[0])
    cmd = CavCommands.idle(25)
    cmd.lane_change[0, cav] = -1
    after = first_env(backend.step(cmd))
    assert after.lane[cav] == 0


def test_cav_speed_change_and_clip():
    backend, state = _cav_backend()
    cmd = CavCommands.idle(25)
    cmd.speed_change_mps[0, state.is_cav] = 2.0
    after = first_env(backend.step(cmd))
    assert np.allclose(after.speed_mps[state.is_cav], state.speed_mps[state.is_cav] + 2.0)
    cmd.speed_change_mps[0, state.is_cav] = 50.0
    after = first_env(
        backend.step(cmd)
    )  # clipped to the 25 m/s limit, reached within the 5 m/s2 limit
    assert np.allclose(after.speed_mps[state.is_cav], 17.0)
    after = first_env(backend.step(cmd))
    assert np.allclose(after.speed_mps[after.is_cav & after.active], 22.0)


def test_cav_driving_into_leader_collides():
    backend = single_lane_backend(2, [40.0, 20.0], [0.0, 20.0])
    backend.state.is_cav[0, 1] = True
    cmd = CavCommands.idle(2)
    pairs = []
    for _ in range(3):
        state = first_env(backend.step(cmd))
        pairs += [tuple(p) for p in state.collisions]
    assert pairs == [(0, 1)]  # reported once, i < j
    assert state.speed_mps[1] == 0.0 and state.active.all()


def test_heading_follows_lateral_motion():
    backend, state = _cav_backend()
    cav = int(np.flatnonzero(state.is_cav & (state.lane < 3))[0])
    cmd = CavCommands.idle(25)
    cmd.lane_change[0, cav] = 1
    moved = first_env(backend.step(cmd))  # heading of the last sub-step: still turning left
    expected = np.arctan2(backend.road.lane_width_m / SIM.step_s, moved.speed_mps[cav])
    assert moved.heading_rad[cav] == pytest.approx(min(expected, backend.model.max_heading_rad))
    straight = first_env(backend.step(CavCommands.idle(25)))
    assert straight.heading_rad[cav] == 0.0


def test_render_non_blank_frame_with_highlight():
    backend, state = _cav_backend()
    for _ in range(3):
        state = backend.step(CavCommands.idle(25))  # the viewer draws a batch of one env
    viewer = Viewer(backend.road, backend.sim)
    frame = viewer.draw(state)
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    assert frame.std() > 5  # not a blank or black frame
    colours = {tuple(c) for c in frame.reshape(-1, 3)[::7]}
    assert len(colours) > 5
    highlighted = viewer.draw(state, highlight=state.is_cav[0])
    assert not np.array_equal(frame, highlighted)
    backend.close()


def test_lane_change_cooldown_counts_down_so_drivers_change_lanes_again():
    """highway-env's LANE_CHANGE_DELAY: a driver who completed a lane change waits
    ``lane_change_cooldown_s`` before choosing another one, then may choose again (before
    2026-12-02 the timer never ran down: one discretionary change per driver and episode)."""
    backend = make("train-50")
    backend.reset(Scenario.with_cavs(25, 0), 3)
    cooldown_s = backend.model.lane_change_cooldown_s
    changes = np.zeros(25, int)
    lane = backend.state.lane_from[0].copy()
    for _ in range(60):
        before = backend.state.cooldown_s[0].copy()
        backend.step(CavCommands.idle(25))
        after = backend.state.cooldown_s[0]
        assert np.all((after >= 0.0) & (after <= cooldown_s))
        # Without a new change within the step (1 s = the delay), every timer has run out.
        same_lane = backend.state.lane_from[0] == lane
        assert np.all(after[(before > 0) & same_lane] == 0.0)
        changes += ~same_lane
        lane = backend.state.lane_from[0].copy()
    assert changes.max() >= 2  # some driver changed lanes more than once


def test_no_lane_change_the_driver_cannot_brake_for():
    """A car cuts in 1.3 m ahead of driver 0; the next lane has a car at 7 m/s 15 m ahead.
    MOBIL's unclipped IDM accelerations rank that lane "better" (both are hopeless), but
    it needs more than the driver's physical braking: no change (before 2026-12-06 the
    driver changed and ran into the slow car; a heuristic crash at 3600 veh/h)."""
    x_m, speed_mps, lanes = [250.0, 256.3, 270.6, 250.0], [22.5, 23.4, 7.3, 22.5], [2, 2, 1, 3]
    unlimited = placed_backend("train-50", x_m, speed_mps, lanes, max_brake_mps2=1e9)
    decide_lane_changes(unlimited)
    assert unlimited.state.lane_to[0, 0] == 1  # a driver who could brake at will would go
    backend = placed_backend("train-50", x_m, speed_mps, lanes)
    decide_lane_changes(backend)
    assert backend.state.lane_to[0].tolist() == lanes
    assert backend.stats["unsafe_change_vetoes"].tolist() == [1]


def test_two_drivers_level_with_each_other_never_enter_one_lane_together():
    """Drivers 0 (lane 0) and 1 (lane 2), side by side at the same x (two cars entering
    in the same sub-step), both want lane 1: only one goes (before 2026-12-06 both did and
    collided, a crash at 4800 veh/h)."""
    backend = placed_backend(
        "train-50", [100.0, 100.0, 120.0, 120.0], [20.0, 20.0, 0.0, 0.0], [0, 2, 0, 2]
    )
    decide_lane_changes(backend)
    assert backend.state.lane_to[0].tolist() == [1, 2, 0, 2]
