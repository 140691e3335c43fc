"""The highway backend's typed state: copies restore a running batch exactly, reset
writes every row, and env rows can be read and written."""

from __future__ import annotations

from dataclasses import fields, is_dataclass

import numpy as np
from test_highway_batch import assert_same_state

from diacc.config import SimConfig, preset_road
from diacc.sim.backends.base import CavCommands
from diacc.sim.backends.highway.backend import HighwayBackend
from diacc.sim.maps import load_map
from diacc.sim.scenario import Scenario

N_ENVS, N_VEHICLES = 2, 25
#: Vehicles enter while the batch runs, so pending/departure fields take part.
DEMAND = Scenario(kind="demand", inflow_vph=3600, demand_s=20, cav_penetration=0.4, cav_slots=4)


def arrays(record, prefix: str = "") -> dict[str, np.ndarray]:
    """Every array field of a record, nested dataclasses (IdmParams) flattened."""
    out = {}
    for f in fields(record):
        value = getattr(record, f.name)
        if is_dataclass(value):
            out.update(arrays(value, f"{f.name}."))
        elif isinstance(value, np.ndarray):
            out[prefix + f.name] = value
    return out


def make_batch(scenario: Scenario) -> HighwayBackend:
    sim = SimConfig()
    batch = HighwayBackend(preset_road(load_map("train-50"), sim.style_preset), sim, n_envs=N_ENVS)
    for e in range(N_ENVS):
        batch.reset(scenario, 5 + e, env=e)
    return batch


def commands(rng: np.random.Generator, n: int) -> CavCommands:
    """Seeded CAV commands: some lane changes, small speed changes."""
    lane = np.where(rng.random((N_ENVS, n)) < 0.1, rng.integers(-1, 2, (N_ENVS, n)), 0)
    return CavCommands(lane.astype(np.int8), rng.normal(0.0, 1.0, (N_ENVS, n)))


def test_copied_records_restore_a_running_batch_exactly():
    batch = make_batch(DEMAND)
    n = batch.state.x_m.shape[1]
    rng = np.random.default_rng(3)
    for _ in range(15):
        batch.step(commands(rng, n))
    saved = (batch.state.copy(), batch.params.copy(), batch.caches.copy())
    saved_stats = {key: counts.copy() for key, counts in batch.stats.items()}
    for record, copy in zip((batch.state, batch.params, batch.caches), saved, strict=True):
        ours, theirs = arrays(record), arrays(copy)
        assert ours.keys() == theirs.keys()
        for name, value in ours.items():
            assert not np.shares_memory(value, theirs[name]), name
    script = [commands(rng, n) for _ in range(30)]
    first = [batch.step(c) for c in script]
    batch.state, batch.params, batch.caches = (r.copy() for r in saved)
    batch.stats = {key: counts.copy() for key, counts in saved_stats.items()}
    again = [batch.step(c) for c in script]
    for t, (a, b) in enumerate(zip(first, again, strict=True)):
        assert_same_state(a, b, f"step {t}")
    assert batch.state.pending.sum() < saved[0].pending.sum()  # vehicles entered meanwhile


def test_reset_of_one_env_writes_every_row_of_state_and_params():
    """A reset env holds exactly what a fresh backend holds after the same reset."""
    scenario = Scenario.with_cavs(N_VEHICLES, 10)
    batch = make_batch(scenario)
    rng = np.random.default_rng(0)
    for _ in range(20):
        batch.step(commands(rng, N_VEHICLES))
    batch.reset(scenario, 77, env=1)
    sim = SimConfig()
    fresh = HighwayBackend(preset_road(load_map("train-50"), sim.style_preset), sim)
    fresh.reset(scenario, 77)
    for ours, theirs in ((batch.state, fresh.state), (batch.params, fresh.params)):
        row, want = arrays(ours.env(1)), arrays(theirs)
        for name, value in want.items():
            assert row[name].dtype == value.dtype, name
            assert np.array_equal(row[name], value), name


def test_env_rows_read_and_write_one_env():
    batch = make_batch(Scenario.with_cavs(N_VEHICLES, 10))
    batch.step(commands(np.random.default_rng(1), N_VEHICLES))
    row = batch.state.env(1)
    assert row.x_m.shape == (1, N_VEHICLES) and row.contact.shape == (1, N_VEHICLES, N_VEHICLES)
    assert row.time_s.shape == (1,)
    before = batch.state.copy()
    batch.state.set_env(0, row)
    for name, value in arrays(batch.state).items():
        assert np.array_equal(value[0], value[1]), name
        assert np.array_equal(value[1], arrays(before)[name][1]), name
