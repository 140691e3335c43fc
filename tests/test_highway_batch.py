"""A batch of highway envs steps each env exactly as a backend of its own would."""

from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest

from diacc.config import SimConfig, preset_road
from diacc.sim.backends.base import BackendError, CavCommands
from diacc.sim.backends.highway.backend import HighwayBackend
from diacc.sim.maps import load_map
from diacc.sim.scenario import Scenario
from diacc.sim.state import TrafficState

N_VEHICLES, N_CAVS, EPISODE_STEPS = 25, 10, 40


def assert_same_state(a: TrafficState, b: TrafficState, where: str) -> None:
    for f in fields(TrafficState):
        va, vb = getattr(a, f.name), getattr(b, f.name)
        same = (
            np.array_equal(va, vb) and va.dtype == vb.dtype
            if isinstance(va, np.ndarray)
            else va == vb
        )
        assert same, f"{where}: {f.name} differs"


@pytest.mark.parametrize(
    ("map_name", "cav_mode"), [("train-25", "commanded"), ("train-50", "cooperative")]
)
def test_batch_equals_separate_backends(map_name, cav_mode):
    """Random CAV commands (collisions, lane changes, arrivals), envs reset at their own ends."""
    sim = SimConfig(cav_mode=cav_mode)
    road = preset_road(load_map(map_name), sim.style_preset)
    scenario = Scenario.with_cavs(N_VEHICLES, N_CAVS)
    n_envs, steps = 4, 150
    batch = HighwayBackend(road, sim, n_envs=n_envs)
    alone = [HighwayBackend(road, sim) for _ in range(n_envs)]
    episodes = [0] * n_envs
    for e in range(n_envs):
        assert_same_state(
            batch.reset_env(e, scenario, 10 * e), alone[e].reset(scenario, 10 * e), "reset"
        )
    rng = np.random.default_rng(0)
    ends = collisions = 0
    for t in range(steps):
        lane = rng.integers(-1, 2, (n_envs, N_VEHICLES)).astype(np.int8)
        speed = rng.normal(0.0, 2.0, (n_envs, N_VEHICLES))
        states = batch.step_batch(CavCommands(lane, speed))
        for e in range(n_envs):
            single = alone[e].step(CavCommands(lane[e], speed[e]))
            assert_same_state(states[e], single, f"step {t} env {e}")
            collisions += len(single.collisions) > 0
            if len(single.collisions) or not single.active.any() or single.step >= EPISODE_STEPS:
                ends += 1
                episodes[e] += 1
                seed = 10 * e + episodes[e]
                assert_same_state(
                    batch.reset_env(e, scenario, seed), alone[e].reset(scenario, seed), "reset"
                )
        for key, counts in batch.stats.items():
            assert list(counts) == [int(b.stats[key][0]) for b in alone], key
    assert ends >= n_envs and (cav_mode == "cooperative" or collisions > 0)  # the test saw events


def test_batch_must_be_stepped_as_a_batch():
    sim = SimConfig()
    batch = HighwayBackend(load_map("train-25"), sim, n_envs=2)
    with pytest.raises(BackendError, match="step_batch"):
        batch.reset(Scenario(), 0)
    batch.reset_env(0, Scenario(), 0)
    with pytest.raises(BackendError, match="reset"):
        batch.step_batch(CavCommands(np.zeros((2, 25), np.int8), np.zeros((2, 25))))
