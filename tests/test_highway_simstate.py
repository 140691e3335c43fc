"""The highway backend's typed state: copies restore a running batch exactly, reset
writes every row, env rows can be read and written, and vehicle windows are cut by
each field's declared axes (an undeclared or misshapen field is an error)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, fields, is_dataclass

import numpy as np
import pytest
from test_highway_batch import assert_same_state

from diacc.config import SimConfig, preset_road
from diacc.sim.backends.base import CavCommands
from diacc.sim.backends.highway.backend import HighwayBackend
from diacc.sim.backends.highway.models import IdmParams
from diacc.sim.backends.highway.rows import Axes, EnvRows, field_axes, per_env, per_vehicle
from diacc.sim.backends.highway.simstate import HighwayCaches, HighwayParams, HighwayState
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
    batch.state.set_rows(np.array([0]), row)
    for name, value in arrays(batch.state).items():
        assert np.array_equal(value[0], value[1]), name
        assert np.array_equal(value[1], arrays(before)[name][1]), name


def test_every_record_field_declares_its_axes():
    for cls in (HighwayState, HighwayParams, HighwayCaches, IdmParams):
        declared = dict(field_axes(cls))
        assert list(declared) == [f.name for f in fields(cls)], cls.__name__
    assert dict(field_axes(HighwayParams))["idm"] is Axes.NESTED
    assert dict(field_axes(HighwayState))["contact"] is Axes.PAIR
    assert dict(field_axes(HighwayState))["time_s"] is Axes.ENV


def test_window_cuts_each_field_by_its_declared_axes_and_writes_back():
    batch = make_batch(DEMAND)
    batch.step(commands(np.random.default_rng(2), batch.state.x_m.shape[1]))
    lo, hi = 3, 11
    for record in (batch.state, batch.params, batch.caches):
        part = record.window(lo, hi)
        for name, kind in field_axes(type(record)):
            whole, cut = getattr(record, name), getattr(part, name)
            if kind is Axes.VEHICLE:
                assert cut.shape == (N_ENVS, hi - lo) and np.shares_memory(cut, whole), name
            elif kind is Axes.PAIR:
                assert cut.shape == (N_ENVS, hi - lo, hi - lo), name
            elif kind is Axes.NESTED:
                assert cut.headway_s.shape == (N_ENVS, hi - lo), name
            else:  # per env or shared: the same object
                assert cut is whole, name
    before = batch.state.copy()
    part = batch.state.window(lo, hi)
    part.x_m = part.x_m + 1.0  # a step replaces arrays of its window
    part.time_s = part.time_s + 0.5
    batch.state.put_window(lo, hi, part)
    shifted = before.x_m.copy()
    shifted[:, lo:hi] += 1.0
    assert np.array_equal(batch.state.x_m, shifted)
    assert np.array_equal(batch.state.time_s, before.time_s + 0.5)


def test_a_field_without_declared_axes_is_an_error():
    @dataclass(slots=True)
    class Loose(EnvRows):
        x_m: np.ndarray = per_vehicle()
        lanes: np.ndarray  # declared nowhere

    record = Loose(np.zeros((2, 5)), np.zeros((2, 3)))
    with pytest.raises(TypeError, match=r"Loose\.lanes declares no axes"):
        record.window(0, 2)


def test_an_array_without_its_declared_axes_is_an_error():
    """Per-env fields with a second axis are not cut as if per vehicle: they are refused."""

    @dataclass(slots=True)
    class Counts(EnvRows):
        per_lane: np.ndarray = per_env()

    with pytest.raises(ValueError, match=r"Counts\.per_lane is declared \(E,\) but holds an "):
        Counts(np.zeros((2, 3))).window(0, 2)
    batch = make_batch(DEMAND)
    state = batch.state
    state.contact = state.contact[:, 0]  # (E, V): not its declared (E, V, V)
    with pytest.raises(ValueError, match=r"HighwayState\.contact is declared \(E, V, V\)"):
        state.window(0, 5)
    params = batch.params
    params.idm = dataclasses.replace(params.idm, headway_s=params.idm.headway_s[:, :, None])
    with pytest.raises(ValueError, match=r"IdmParams\.headway_s is declared \(E, V\)"):
        params.window(0, 5)
    caches = batch.caches
    part = caches.window(0, 5)
    part.leaders_dirty = np.ones((N_ENVS, 5), bool)  # a stepped window that grew an axis
    with pytest.raises(ValueError, match=r"HighwayCaches\.leaders_dirty is declared \(E,\)"):
        caches.put_window(0, 5, part)
