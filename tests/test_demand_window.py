"""Demand scenarios scale with the vehicles on the road, not with the episode's V:
the critic holds the on-road vehicles first (compact rows, so obs.max_vehicles
bounds those on the road at once), the neighbour search and the safety events
look at the on-road window alone with the same results, the GAT gathers for
large graphs; a release keeps its layout (row i = vehicle i)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from helpers import SHORT_MAP
from test_demand import tiny_demand_run

import diacc.envs.observation.frames as observation_frames
import diacc.envs.safety as safety
import diacc.learn.models.gat as gat
from diacc.config import EnvConfig, EventConfig, ObservationConfig, SimConfig
from diacc.envs.actions import LANE_RIGHT
from diacc.envs.env import BottleneckEnv
from diacc.envs.observation import ObservationBuilder, ObservationError
from diacc.sim.scenario import Scenario
from diacc.sim.state import TrafficState, on_road_window

#: 60 vehicles over 60 s on a 160 m road: about ten on the road at once.
DEMAND = Scenario(kind="demand", inflow_vph=3600, demand_s=60, cav_penetration=0.4, cav_slots=4)
STEPS = 70


@pytest.fixture
def short_map(tmp_path):
    path = tmp_path / "short.toml"
    path.write_text(SHORT_MAP)
    return str(path)


def env_config(road: str, scenario: Scenario, max_vehicles: int) -> EnvConfig:
    return EnvConfig(
        backend="highway",
        map=road,
        scenario=scenario,
        sim=SimConfig(episode_steps=STEPS, style_preset="zipper"),
        obs=ObservationConfig(max_vehicles=max_vehicles),
    )


def episode(config: EnvConfig, seed: int = 4):
    """(state, critic state) of every step of one episode, CAVs keeping right."""
    env = BottleneckEnv(config)
    try:
        _, critic = env.reset_arrays(seed)
        out = [(env.state_, critic)]
        for _ in range(STEPS):
            step = env.step_arrays(np.full(env.n_cavs, LANE_RIGHT))
            out.append((step.state, step.critic_state))
            if step.terminated or step.truncated:
                break
        return env, out
    finally:
        env.close()


def test_demand_critic_rows_hold_the_vehicles_on_the_road_first(short_map):
    """Each compact row is the full layout's row of its vehicle, neighbours renumbered."""
    env, steps = episode(env_config(short_map, DEMAND, max_vehicles=24))
    assert env.batch.builder.compact_critic
    n_veh = DEMAND.n_vehicles
    reference = ObservationBuilder(env.road, ObservationConfig(max_vehicles=n_veh), STEPS)
    on_road = []
    for t, (state, critic) in enumerate(steps):
        (reference.reset if t == 0 else reference.push)(state)
        full = reference.critic().unbatched(0)  # state: a batch of one env
        vehicles = np.flatnonzero(state.active[0])  # (n,) on the road, in index order
        n = len(vehicles)
        on_road.append(n)
        assert critic.nodes.shape == (24, 6)
        np.testing.assert_array_equal(critic.node_mask, np.arange(24) < n)
        np.testing.assert_array_equal(critic.nodes[:n], full.nodes[vehicles])
        assert not critic.nodes[n:].any() and not critic.neighbours[n:].any()
        row_of = np.zeros(n_veh, np.int64)
        row_of[vehicles] = np.arange(n)
        mask = full.neighbour_mask[vehicles]
        np.testing.assert_array_equal(critic.neighbour_mask[:n], mask)
        np.testing.assert_array_equal(
            critic.neighbours[:n], np.where(mask, row_of[full.neighbours[vehicles]], 0)
        )
        assert not critic.neighbour_mask[n:].any()
        np.testing.assert_array_equal(critic.lane_stats, full.lane_stats)
        np.testing.assert_array_equal(critic.traffic[1:], full.traffic[1:])
    # Vehicles came and left: far more in the episode than on the road at once.
    assert steps[-1][0].arrived.sum() > 24 and 0 < max(on_road) <= 24


def test_too_many_vehicles_on_the_road_is_a_one_line_error(short_map):
    with pytest.raises(ObservationError, match="on the road but ObservationConfig.max_vehicles"):
        episode(env_config(short_map, DEMAND, max_vehicles=2))


def test_release_critic_layout_is_unchanged(short_map):
    """Row i is vehicle i for the whole episode; inactive rows zero and masked."""
    release = Scenario.with_cavs(12, 4)
    env, steps = episode(env_config(short_map, release, max_vehicles=40))
    assert not env.batch.builder.compact_critic
    for state, critic in steps:
        np.testing.assert_array_equal(critic.node_mask[:12], state.active[0])
        assert not critic.node_mask[12:].any()
        x = np.where(state.active[0], state.x_m[0] / env.road.length_m, 0.0).astype(np.float32)
        np.testing.assert_array_equal(critic.nodes[:12, 0], np.clip(x, -5, 5))
    assert steps[-1][0].arrived.any()


def all_vehicles(active: np.ndarray) -> tuple[int, int]:
    """The window of every vehicle: the searches as they were before the window."""
    return 0, active.shape[-1]


def test_window_searches_equal_searches_over_all_vehicles(short_map, monkeypatch):
    """Neighbour sets and safety events, single states and batches, demand and release."""
    _, demand = episode(env_config(short_map, DEMAND, max_vehicles=24))
    states = [state for state, _ in demand]
    batches = [TrafficState.concat([a, b]) for a, b in zip(states[::2], states[1::2], strict=False)]
    empty = states[0].copy()
    empty.active[:] = False
    assert on_road_window(empty.active) == (0, 0)
    builder = ObservationBuilder(
        BottleneckEnv(env_config(short_map, DEMAND, 24)).road, ObservationConfig(), STEPS
    )
    cases = states + batches + [empty]
    windowed = [
        (builder._neighbours(s), safety.safety_critical_events(s, EventConfig())) for s in cases
    ]
    assert any(0 < on_road_window(s.active)[0] for s in cases)  # the window left vehicles out
    monkeypatch.setattr(observation_frames, "on_road_window", all_vehicles)
    monkeypatch.setattr(safety, "on_road_window", all_vehicles)
    for s, (nbr, events) in zip(cases, windowed, strict=True):
        for a, b in zip(nbr, builder._neighbours(s), strict=True):
            np.testing.assert_array_equal(a, b)
        full = safety.safety_critical_events(s, EventConfig())
        for name in ("small_gap", "low_ttc", "collision", "emergency_brake"):
            np.testing.assert_array_equal(getattr(events, name), getattr(full, name))


@pytest.mark.parametrize("concat", [False, True])
def test_gat_gathers_large_graphs_as_the_dense_matrix_would(concat, monkeypatch):
    torch.manual_seed(0)
    layer = gat.GraphAttention(10, 8, 3, concat=concat)
    n_batch, n_nodes, k = 3, gat.DENSE_MAX_NODES + 26, 6
    args = (
        torch.randn(n_batch, n_nodes, 10),
        torch.randint(0, n_nodes, (n_batch, n_nodes, k)),
        torch.rand(n_batch, n_nodes, k) < 0.7,
        torch.rand(n_batch, n_nodes) < 0.8,
    )
    gathered = layer.forward_graph(*args)
    monkeypatch.setattr(gat, "DENSE_MAX_NODES", n_nodes)
    dense = layer.forward_graph(*args)
    torch.testing.assert_close(gathered, dense, rtol=1e-5, atol=1e-6)
    assert gathered[~args[3]].abs().max() == 0  # masked nodes stay zero


def test_demand_training_with_fewer_critic_rows_than_vehicles(tmp_path, short_map):
    """max_vehicles 40 < N = 60: a few updates train, and the checkpoint evaluates."""
    settings = {"env.backend": "highway", "env.obs.max_vehicles": 40}
    metrics = tiny_demand_run(tmp_path, short_map, DEMAND, STEPS, 3, **settings)
    assert metrics.n_vehicles > 40 and np.isfinite(metrics.mean_speed_mps)
