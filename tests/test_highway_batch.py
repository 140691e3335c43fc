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
            batch.reset(scenario, 10 * e, env=e), alone[e].reset(scenario, 10 * e), "reset"
        )
    rng = np.random.default_rng(0)
    ends = collisions = 0
    for t in range(steps):
        lane = rng.integers(-1, 2, (n_envs, N_VEHICLES)).astype(np.int8)
        speed = rng.normal(0.0, 2.0, (n_envs, N_VEHICLES))
        commands = CavCommands(lane, speed)
        states = batch.step(commands)
        for e in range(n_envs):
            single = alone[e].step(commands.env(e))
            assert_same_state(states.env(e), single, f"step {t} env {e}")
            collisions += len(single.collisions) > 0
            if len(single.collisions) or not single.active.any() or single.step[0] >= EPISODE_STEPS:
                ends += 1
                episodes[e] += 1
                seed = 10 * e + episodes[e]
                assert_same_state(
                    batch.reset(scenario, seed, env=e), alone[e].reset(scenario, seed), "reset"
                )
        for key, counts in batch.stats.items():
            assert list(counts) == [int(b.stats[key][0]) for b in alone], key
    assert ends >= n_envs and (cav_mode == "cooperative" or collisions > 0)  # the test saw events


def test_batch_is_reset_env_by_env_and_stepped_whole():
    sim = SimConfig()
    batch = HighwayBackend(load_map("train-25"), sim, n_envs=2)
    with pytest.raises(BackendError, match="env 2 is not one of the backend's 2"):
        batch.reset(Scenario(), 0, env=2)
    first = batch.reset(Scenario(), 0)
    assert first.n_envs == 1 and first.x_m.shape == (1, 25)
    with pytest.raises(BackendError, match="reset"):
        batch.step(CavCommands.idle(25, n_envs=2))
    batch.reset(Scenario(), 1, env=1)
    with pytest.raises(BackendError, match=r"commands must have shape \(2, 25\)"):
        batch.step(CavCommands.idle(25))
    assert batch.step(CavCommands.idle(25, n_envs=2)).x_m.shape == (2, 25)
