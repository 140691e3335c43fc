"""The highway backend's active window (HighwayBackend._window) changes no result:
stepping only the vehicles not settled gives the same states, bit for bit, as
stepping all of them, on demand and release scenarios, single and batched."""

from __future__ import annotations

import numpy as np
import pytest
from test_highway_batch import assert_same_state

from diacc.config import SimConfig, preset_road
from diacc.sim.backends.base import CavCommands
from diacc.sim.backends.highway.backend import HighwayBackend
from diacc.sim.maps import load_map
from diacc.sim.scenario import Scenario

#: About 90 vehicles, the first ones arrive after about 60 s: the window moves at both ends.
DEMAND = Scenario(kind="demand", inflow_vph=3600, demand_s=90, cav_penetration=0.4, cav_slots=6)
RELEASE = Scenario.with_cavs(25, 10)


def make_pair(scenario: Scenario, n_envs: int, cav_mode: str, seed: int):
    """Two identical batches: one steps every vehicle, the other only its window (always)."""
    sim = SimConfig(cav_mode=cav_mode, style_preset="zipper")
    road = preset_road(load_map("train-50"), sim.style_preset)
    full, windowed = (HighwayBackend(road, sim, n_envs=n_envs) for _ in range(2))
    full.windowed = False
    windowed.window_min_vehicles = 0  # window even the small release batch
    for e in range(n_envs):
        assert_same_state(
            full.reset(scenario, seed + e, env=e),
            windowed.reset(scenario, seed + e, env=e),
            "reset",
        )
    return full, windowed


def env_commands(
    rng: np.random.Generator, batch: HighwayBackend, commanded: np.ndarray
) -> CavCommands:
    """Commands as the env gives them: the (E, 1) ``commanded`` share of the CAVs on the
    road a seeded lane change (rarely) and speed change, the others none (NaN: they
    drive themselves); 0 for every other vehicle. Commanded CAVs stop at lane ends and
    crash (wrecks stay on the road), so fully self-driven envs keep the window moving."""
    state, params = batch.state, batch.params
    shape = state.x_m.shape
    on_road_cav = params.reported_cav & state.active
    lane = np.where(on_road_cav & (rng.random(shape) < 0.03), rng.integers(-1, 2, shape), 0)
    speed = np.where(on_road_cav, rng.normal(0.0, 1.0, shape), 0.0)
    speed[on_road_cav & (rng.random(shape) >= commanded)] = np.nan
    return CavCommands(lane.astype(np.int8), speed)


def run_pair(
    scenario: Scenario, cav_mode: str, seed: int, steps: int, commanded: list[float]
) -> np.ndarray:
    """Step both batches alike, env e with the ``commanded[e]`` share of its CAVs given
    commands; returns the (steps, 2) windows of the steps (so a test can check that
    the window left vehicles out). Envs restart at their own ends: when every vehicle
    has left or after ``seed``-dependent lengths; a collision does not end one here
    (its wrecks stay on the road as obstacles and keep the window open)."""
    n_envs = len(commanded)
    full, windowed = make_pair(scenario, n_envs, cav_mode, seed)
    rng = np.random.default_rng(seed)
    episodes, windows = [0] * n_envs, []
    for t in range(steps):
        windows.append(windowed._window())
        commands = env_commands(rng, full, np.array(commanded)[:, None])
        a, b = full.step(commands), windowed.step(commands)
        assert_same_state(a, b, f"step {t}")
        for e in range(n_envs):
            if a.arrived[e].all() or a.step[e] >= 120 + 10 * e:
                episodes[e] += 1
                again = seed + 100 * episodes[e] + e
                assert_same_state(
                    full.reset(scenario, again, env=e),
                    windowed.reset(scenario, again, env=e),
                    "reset",
                )
        for key, counts in full.stats.items():
            assert np.array_equal(counts, windowed.stats[key]), key
    return np.array(windows)


def assert_window_moved(windows: np.ndarray, n_vehicles: int) -> None:
    """The window left out arrived vehicles and vehicles still to come, often."""
    assert windows[:, 0].max() > 0 and (windows[:, 1] < n_vehicles).sum() > 50


@pytest.mark.parametrize(("seed", "commanded"), [(0, 0.0), (1, 0.0), (2, 0.3)])
def test_window_single_demand_env_is_exact(seed, commanded):
    windows = run_pair(DEMAND, "commanded", seed, steps=160, commanded=[commanded])
    assert_window_moved(windows, DEMAND.n_vehicles)


@pytest.mark.parametrize("cav_mode", ["commanded", "cooperative"])
def test_window_batched_demand_envs_are_exact(cav_mode):
    """Three envs restarting at different steps: the union window jumps back at each reset."""
    windows = run_pair(DEMAND, cav_mode, 7, steps=220, commanded=[0.0, 0.0, 0.5])
    assert_window_moved(windows, DEMAND.n_vehicles)


def test_window_release_is_exact():
    windows = run_pair(RELEASE, "commanded", 3, steps=120, commanded=[0.0, 0.2])
    assert windows[:, 0].max() > 0


def test_release_batches_are_never_windowed_by_default():
    """N = 25 < window_min_vehicles: a release steps all vehicles as before."""
    sim = SimConfig()
    batch = HighwayBackend(load_map("train-50"), sim)
    batch.reset(RELEASE, 0)
    for _ in range(60):
        batch.step(CavCommands.idle(25))
        assert batch._window() == (0, 25)
