"""Observation builder: neighbour rule, history, masks, lane statistics, critic, backends."""

from __future__ import annotations

import helpers
import numpy as np
import pytest

from diacc.config import ObservationConfig, SimConfig
from diacc.envs.observation import (
    DX_SCALE_M,
    FEATURE_CLIP,
    MAX_LANES,
    MAX_SEGMENTS,
    ActorObs,
    CriticState,
    ObservationError,
    ObservationSpec,
)
from diacc.envs.observation import ObservationBuilder as BatchBuilder
from diacc.sim.backends.base import CavCommands, make_backend
from diacc.sim.maps import load_map, parse_map
from diacc.sim.scenario import Scenario
from diacc.sim.state import TrafficState

CFG = ObservationConfig()
K, T = CFG.n_neighbours, CFG.history_steps
# Node feature columns (module docstring): dx, dy, dv, heading, v, is_cav.
DX, DY, DV, HEAD, V, IS_CAV = range(6)


class ObservationBuilder(BatchBuilder):
    """The builder on E = 1 batches, read as one env: (C,) slot and (V,) vehicle arrays
    in, env 0 of every output (what the tests below compare)."""

    def actor(self, cav_index, memory, prev_action):
        arrays = (np.asarray(cav_index)[None], memory[None], prev_action[None])
        return helpers.first_env(super().actor(*arrays))

    def critic(self):
        return helpers.first_env(super().critic())

    @property
    def neighbours(self):
        return helpers.first_env(super().neighbours)


@pytest.fixture(scope="module")
def road():
    """Training map: 4 lanes, lanes 3 dropped (drop_side left) on 500-800 m."""
    return load_map("train-25")


def make_state(road, x_m, lane, is_cav, speed_mps=20.0, active=True, step=0) -> TrafficState:
    """Shared ``helpers.make_state`` with the segment and lane width taken from ``road``."""
    return helpers.make_state(
        x_m,
        lane,
        speed_mps,
        is_cav=is_cav,
        active=active,
        segment=road.segment_of(np.asarray(x_m, np.float64)),
        lane_width_m=road.lane_width_m,
        time_s=float(step),
        step=step,
    )


def random_state(road, n, n_cav, seed, step=0) -> TrafficState:
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.0, road.length_m, n)
    seg = road.segment_of(x)
    first = np.array([road.first_lane(s) for s in seg])
    n_lanes = np.array([road.segments[s].lanes for s in seg])
    lane = first + rng.integers(0, 1 << 20, n) % n_lanes
    active = rng.random(n) > 0.1
    return make_state(road, x, lane, np.arange(n) < n_cav, rng.uniform(0.0, 25.0, n), active, step)


def build(road, state, cav_index, cfg=CFG):
    b = ObservationBuilder(road, cfg, episode_steps=100)
    b.reset(state)
    c = len(cav_index)
    obs = b.actor(
        np.asarray(cav_index), np.zeros((c, 2), np.int64), np.zeros(state.n_vehicles, np.int64)
    )
    return b, obs


def current_x(obs: ActorObs, nodes: np.ndarray, ego_x: np.ndarray) -> np.ndarray:
    """Absolute current x of each node from its relative dx feature: (C, K).

    Exact only for neighbours within FEATURE_CLIP * DX_SCALE_M (250 m).
    """
    return nodes[:, :, -1, DX] * DX_SCALE_M + ego_x[:, None]


def dx_feature(x_m: np.ndarray, ego_x_m: float) -> np.ndarray:
    """The documented dx feature (clipped) of vehicles at ``x_m``."""
    return np.clip((np.asarray(x_m) - ego_x_m) / DX_SCALE_M, -FEATURE_CLIP, FEATURE_CLIP)


def reference_neighbours(state: TrafficState, i: int, k: int) -> list[int]:
    """Plain-loop reference of the neighbour rule."""
    cands = [
        j
        for j in range(state.n_vehicles)
        if j != i
        and state.active[0][j]
        and state.active[0][i]
        and abs(int(state.lane[0][j]) - int(state.lane[0][i])) <= 1
    ]
    cands.sort(key=lambda j: (abs(state.x_m[0][j] - state.x_m[0][i]), j))
    return cands[:k]


# ---------------------------------------------------------------------------
# Neighbour selection
# ---------------------------------------------------------------------------
def test_picks_six_nearest_in_same_and_adjacent_lanes_split_by_type(road):
    # Ego 0: CAV at x = 300 in lane 1. Distances chosen distinct.
    #            ego   h    c    h    h    c    h    h    c    h    h    h
    x = [300, 303, 295, 310, 288, 315, 280, 330, 340, 301, 299, 302]
    lane = [1, 1, 2, 0, 1, 2, 0, 1, 1, 3, 3, 0]
    cav = [1, 0, 1, 0, 0, 1, 0, 0, 1, 0, 0, 0]
    active = [1] * 11 + [0]  # vehicle 11 is close but not on the road
    state = make_state(road, x, lane, cav, active=active)
    b, obs = build(road, state, [0])
    # Eligible by |dx|: 1 (3), 2 (5), 3 (10), 4 (12), 5 (15), 6 (20), 7 (30), 8 (40);
    # 9, 10 are two lanes away, 11 inactive.
    nearest = [1, 2, 3, 4, 5, 6]
    assert b.neighbours[0][0].tolist() == nearest
    assert b.neighbours[1][0].all()
    hdv_x = current_x(obs, obs.hdv_nodes, np.array([300.0]))[0]
    cav_x = current_x(obs, obs.cav_nodes, np.array([300.0]))[0]
    assert obs.hdv_mask[0].tolist() == [True] * 4 + [False] * 2
    assert obs.cav_mask[0].tolist() == [True] * 2 + [False] * 4
    np.testing.assert_allclose(hdv_x[:4], [303, 310, 288, 280], atol=1e-3)  # nearest first
    np.testing.assert_allclose(cav_x[:2], [295, 315], atol=1e-3)
    assert np.all(obs.hdv_nodes[0, :4, :, IS_CAV] == 0.0)
    assert np.all(obs.cav_nodes[0, :2, :, IS_CAV] == 1.0)
    # dy is in lane widths: vehicle 2 is one lane to the left.
    assert obs.cav_nodes[0, 0, -1, DY] == pytest.approx(1.0)
    assert obs.hdv_nodes[0, 1, -1, DY] == pytest.approx(-1.0)


@pytest.mark.parametrize("seed", range(5))
def test_neighbours_match_plain_loop_reference(road, seed):
    state = random_state(road, 40, 16, seed)
    b, obs = build(road, state, np.arange(16))
    idx, mask = b.neighbours
    for i in range(state.n_vehicles):
        ref = reference_neighbours(state, i, K)
        assert idx[i][mask[i]].tolist() == ref
        assert np.all(idx[i][~mask[i]] == 0)
    # Actor sets, merged back by distance, are exactly the critic's neighbour rows.
    for c in range(16):
        got = np.concatenate(
            [obs.hdv_nodes[c, obs.hdv_mask[c], -1, DX], obs.cav_nodes[c, obs.cav_mask[c], -1, DX]]
        )
        ref = dx_feature(state.x_m[0][reference_neighbours(state, c, K)], state.x_m[0][c])
        np.testing.assert_allclose(np.sort(got), np.sort(ref), atol=1e-5)


def test_critic_neighbours_consistent_with_actor(road):
    state = random_state(road, 25, 10, seed=7)
    b, obs = build(road, state, np.arange(10))
    crit = b.critic()
    for c in range(10):
        ids = crit.neighbours[c][crit.neighbour_mask[c]]
        assert obs.hdv_mask[c].sum() + obs.cav_mask[c].sum() == len(ids)
        hdv_ids = [j for j in ids if not state.is_cav[0][j]]
        cav_ids = [j for j in ids if state.is_cav[0][j]]
        ego = state.x_m[0][c]
        np.testing.assert_allclose(
            obs.hdv_nodes[c, obs.hdv_mask[c], -1, DX],
            dx_feature(state.x_m[0][hdv_ids], ego),
            atol=1e-5,
        )
        np.testing.assert_allclose(
            obs.cav_nodes[c, obs.cav_mask[c], -1, DX],
            dx_feature(state.x_m[0][cav_ids], ego),
            atol=1e-5,
        )
    # Every edge joins two active vehicles in same/adjacent lanes.
    i, k = np.nonzero(crit.neighbour_mask)
    j = crit.neighbours[i, k]
    assert np.all(state.active[0][i] & state.active[0][j])
    assert np.all(np.abs(state.lane[0][i].astype(int) - state.lane[0][j]) <= 1)
    assert np.all(i != j)


# ---------------------------------------------------------------------------
# History
# ---------------------------------------------------------------------------
def test_history_shifts_after_push(road):
    x0 = np.array([100.0, 120.0, 90.0])
    lane, cav = [1, 1, 2], [1, 0, 1]
    b = ObservationBuilder(road, CFG, episode_steps=100)
    states = [
        make_state(
            road, x0 + 10.0 * t + [0, 2 * t, 0], lane, cav, speed_mps=[10 + t, 12, 8], step=t
        )
        for t in range(T + 2)
    ]
    b.reset(states[0])

    def actor():
        return b.actor(np.array([0]), np.zeros((1, 2), np.int64), np.zeros(3, np.int64))

    obs = actor()
    # At reset every history entry is the first state: zero relative motion.
    assert np.all(obs.ego_hist[0, :, DX] == 0.0)
    np.testing.assert_allclose(obs.hdv_nodes[0, 0, :, DX], 20.0 / DX_SCALE_M, atol=1e-6)
    for t in range(1, T + 2):
        b.push(states[t])
        obs = actor()
        ego_x_now = states[t].x_m[0][0]
        # Entry -1 - s holds step max(t - s, 0).
        past = [max(t - s, 0) for s in range(T)][::-1]  # oldest first
        np.testing.assert_allclose(
            obs.ego_hist[0, :, DX],
            [(states[p].x_m[0][0] - ego_x_now) / DX_SCALE_M for p in past],
            atol=1e-5,
        )
        np.testing.assert_allclose(
            obs.ego_hist[0, :, V], [states[p].speed_mps[0][0] / 25.0 for p in past], atol=1e-6
        )
        np.testing.assert_allclose(
            obs.hdv_nodes[0, 0, :, DX],
            [(states[p].x_m[0][1] - ego_x_now) / DX_SCALE_M for p in past],
            atol=1e-5,
        )
        np.testing.assert_allclose(
            obs.hdv_nodes[0, 0, :, DV], [(12.0 - states[t].speed_mps[0][0]) / 25.0] * T, atol=1e-6
        )
    assert obs.ego_hist[0, -1, DX] == 0.0 and obs.ego_hist[0, -1, DV] == 0.0


def test_history_uses_earliest_values_for_late_vehicles(road):
    b = ObservationBuilder(road, CFG, episode_steps=100)
    s0 = make_state(road, [100.0, 130.0], [1, 1], [1, 0], active=[1, 0])
    s1 = make_state(road, [110.0, 140.0], [1, 1], [1, 0], step=1)
    b.reset(s0)
    b.push(s1)
    obs = b.actor(np.array([0]), np.zeros((1, 2), np.int64), np.zeros(2, np.int64))
    # Vehicle 1 was inactive at every older entry: all entries repeat its step-1 value.
    np.testing.assert_allclose(obs.hdv_nodes[0, 0, :, DX], 30.0 / DX_SCALE_M, atol=1e-6)


# ---------------------------------------------------------------------------
# Padding and masks
# ---------------------------------------------------------------------------
def test_padding_nodes_are_zero_and_masked(road):
    state = make_state(road, [200.0, 210.0, 400.0, 205.0], [1, 1, 1, 3], [1, 0, 1, 0])
    b, obs = build(road, state, [0, 2])
    assert obs.hdv_mask.tolist() == [[True] + [False] * 5, [True] + [False] * 5]
    assert obs.cav_mask.tolist() == [[True] + [False] * 5, [True] + [False] * 5]
    assert np.all(obs.hdv_nodes[:, 1:] == 0.0) and np.all(obs.cav_nodes[:, 1:] == 0.0)
    assert np.all(obs.cav_prev_action[:, 1:] == 0)
    crit = b.critic()
    assert crit.node_mask.tolist() == [True] * 4 + [False] * (CFG.max_vehicles - 4)
    assert np.all(crit.nodes[4:] == 0.0)
    assert np.all(crit.neighbours[~crit.neighbour_mask] == 0)
    assert crit.neighbour_mask[3].sum() == 0  # lane 3 is two lanes from everyone else


def test_cav_prev_action_reads_neighbour_cavs(road):
    state = make_state(road, [200.0, 210.0, 220.0, 190.0], [1, 1, 2, 0], [1, 1, 0, 1])
    b = ObservationBuilder(road, CFG, episode_steps=100)
    b.reset(state)
    memory = np.array([[3, 4], [1, 0]], np.int64)
    obs = b.actor(np.array([0, 1]), memory, np.array([0, 2, 4, 3], np.int64))
    assert obs.cav_prev_action[0].tolist() == [2, 3, 0, 0, 0, 0]  # vehicle 1 then 3
    assert obs.action_memory.tolist() == memory.tolist()


def test_dead_cav_row_is_zero(road):
    state = make_state(road, [200.0, 210.0, 220.0], [1, 1, 1], [1, 1, 0], active=[1, 0, 1])
    b, obs = build(road, state, [0, 1])
    assert obs.alive.tolist() == [True, False]
    for name in ("self_state", "ego_hist", "hdv_nodes", "cav_nodes", "lane_stats", "road"):
        assert np.all(getattr(obs, name)[1] == 0.0), name
    for name in ("hdv_mask", "cav_mask", "lane_mask"):
        assert not getattr(obs, name)[1].any(), name
    assert not obs.cav_mask[0].any()  # the dead CAV is nobody's neighbour


# ---------------------------------------------------------------------------
# Lane statistics and self features
# ---------------------------------------------------------------------------
def test_leftmost_lane_has_empty_masked_left_statistic(road):
    state = make_state(road, [200.0, 220.0, 180.0], [3, 3, 2], [1, 0, 1])
    _, obs = build(road, state, [0])
    assert obs.lane_mask[0].tolist() == [True, False, True]  # ego, left, right
    assert np.all(obs.lane_stats[0, 1] == 0.0)
    # Ego lane: one other vehicle (the HDV 20 m ahead); right lane: one CAV.
    np.testing.assert_allclose(obs.lane_stats[0, 0], [0.1, 1 / 0.2 / 100, 20 / 25, 0.0], atol=1e-6)
    np.testing.assert_allclose(obs.lane_stats[0, 2], [0.1, 1 / 0.2 / 100, 20 / 25, 1.0], atol=1e-6)
    assert obs.self_state[0, 4] == pytest.approx(1.0)  # lane / (max_lanes - 1)


def test_rightmost_lane_has_masked_right_statistic(road):
    state = make_state(road, [200.0, 205.0], [0, 0], [1, 0])
    _, obs = build(road, state, [0])
    assert obs.lane_mask[0].tolist() == [True, True, False]
    assert np.all(obs.lane_stats[0, 2] == 0.0)
    assert np.all(obs.lane_stats[0, 1] == 0.0)  # left lane exists but is empty


def test_lane_dropped_in_current_segment_is_masked(road):
    # train-25: lane 3 exists on 0-500 m, not on 500-800 m. Ego at 510 m in lane 2
    # has a vehicle in lane 3 at 490 m, inside the window, but the lane is gone here.
    state = make_state(
        road, [510.0, 490.0, 520.0], [2, 3, 1], [1, 0, 0], speed_mps=[20.0, 10.0, 16.0]
    )
    _, obs = build(road, state, [0, 1])
    assert obs.lane_mask[0].tolist() == [True, False, True]
    assert np.all(obs.lane_stats[0, 1] == 0.0)
    np.testing.assert_allclose(obs.lane_stats[0, 2, 2], 16.0 / 25.0, atol=1e-6)
    # Self feature: vehicle 1 (not a CAV slot normally; used here) is 10 m before its lane end.
    assert obs.self_state[1, 5] == pytest.approx(0.1)
    assert obs.self_state[0, 5] == pytest.approx(1.0)


def test_lane_statistics_window_and_density(road):
    # Window +-100 m around x = 50: covers 0..150 m = 0.15 km of road.
    x = [50.0, 60.0, 140.0, 160.0, 70.0]
    state = make_state(
        road, x, [1, 1, 1, 1, 1], [1, 1, 0, 0, 0], speed_mps=[5.0, 10.0, 20.0, 25.0, 15.0]
    )
    _, obs = build(road, state, [0])
    count = 3  # 60, 140, 70; 160 is outside the window, the ego is excluded
    np.testing.assert_allclose(
        obs.lane_stats[0, 0],
        [count / 10, count / 0.15 / 100, (10 + 20 + 15) / 3 / 25, 1 / 3],
        atol=1e-5,
    )


def test_critic_lane_stats_and_traffic(road):
    state = make_state(
        road,
        [100.0, 200.0, 300.0, 400.0, 600.0],
        [0, 0, 1, 3, 2],
        [1, 0, 0, 1, 1],
        speed_mps=[10.0, 20.0, 15.0, 5.0, 25.0],
        active=[1, 1, 1, 1, 0],
        step=25,
    )
    b, _ = build(road, state, [0, 3, 4])
    crit = b.critic()
    assert crit.lane_mask.tolist() == [True] * 4 + [False] * (MAX_LANES - 4)
    np.testing.assert_allclose(crit.lane_stats[0], [0.2, 2 / 1.3 / 100, 15 / 25, 0.5], atol=1e-6)
    np.testing.assert_allclose(crit.lane_stats[3], [0.1, 1 / 1.0 / 100, 5 / 25, 1.0], atol=1e-6)
    assert np.all(crit.lane_stats[2] == 0.0)  # only an inactive vehicle there
    assert np.all(crit.lane_stats[4:] == 0.0)
    np.testing.assert_allclose(crit.traffic, [4 / 40, 12.5 / 25, 0.5, 0.25], atol=1e-6)
    road_table = crit.road.reshape(MAX_SEGMENTS, 4)
    np.testing.assert_allclose(road_table[:3, 0], [0.0, 500 / 1300, 800 / 1300], atol=1e-6)
    np.testing.assert_allclose(road_table[:3, 2], [1.0, 0.75, 1.0], atol=1e-6)
    assert np.all(road_table[3:] == 0.0) and np.all(road_table[:3, 3] == 1.0)


# ---------------------------------------------------------------------------
# Layout, ranges, errors
# ---------------------------------------------------------------------------
def check_layout(obs: ActorObs, crit: CriticState, n_cav: int, cfg=CFG) -> None:
    spec = ObservationSpec.from_config(cfg)
    for name, (shape, dtype) in spec.actor_shapes(n_cav).items():
        arr = getattr(obs, name)
        assert arr.shape == shape and arr.dtype == dtype, (name, arr.shape, arr.dtype)
    for name, (shape, dtype) in spec.critic_shapes().items():
        arr = getattr(crit, name)
        assert arr.shape == shape and arr.dtype == dtype, (name, arr.shape, arr.dtype)
    for arr in [*vars(obs).values(), *vars(crit).values()]:
        if arr.dtype == np.float32:
            assert np.all(np.isfinite(arr)) and np.all(np.abs(arr) <= FEATURE_CLIP)
    # Masked-out entries are exactly zero.
    assert np.all(obs.hdv_nodes[~obs.hdv_mask] == 0.0)
    assert np.all(obs.cav_nodes[~obs.cav_mask] == 0.0)
    assert np.all(obs.lane_stats[~obs.lane_mask] == 0.0)
    assert np.all(crit.nodes[~crit.node_mask] == 0.0)
    assert np.all(crit.lane_stats[~crit.lane_mask] == 0.0)
    # Actor masks: type split is right; critic masks only point at active nodes.
    assert np.all(obs.hdv_nodes[obs.hdv_mask][:, :, IS_CAV] == 0.0)
    assert np.all(obs.cav_nodes[obs.cav_mask][:, :, IS_CAV] == 1.0)
    assert np.all(crit.node_mask[crit.neighbours[crit.neighbour_mask]])


@pytest.mark.parametrize(("n", "n_cav"), [(25, 10), (40, 16), (3, 1)])
def test_shapes_dtypes_and_ranges(road, n, n_cav):
    state = random_state(road, n, n_cav, seed=n)
    b, obs = build(road, state, np.arange(n_cav))
    for t in range(1, 4):
        b.push(random_state(road, n, n_cav, seed=100 + t, step=t))
    obs = b.actor(np.arange(n_cav), np.zeros((n_cav, 2), np.int64), np.zeros(n, np.int64))
    check_layout(obs, b.critic(), n_cav)
    assert b.spec() == ObservationSpec.from_config(CFG)


def test_far_neighbours_are_clipped_not_dropped(road):
    state = make_state(road, [10.0, 1290.0], [1, 1], [1, 0])
    _, obs = build(road, state, [0])
    assert obs.hdv_mask[0, 0] and obs.hdv_nodes[0, 0, -1, DX] == FEATURE_CLIP


def test_bad_inputs_raise_clear_errors(road):
    big = random_state(road, 41, 5, seed=0)
    b = ObservationBuilder(road, CFG, episode_steps=100)
    with pytest.raises(ObservationError, match="max_vehicles"):
        b.reset(big)
    with pytest.raises(ObservationError, match="before reset"):
        b.push(random_state(road, 5, 1, seed=0))
    with pytest.raises(ObservationError, match="no state"):
        b.critic()
    b.reset(random_state(road, 5, 1, seed=0))
    with pytest.raises(ObservationError, match="episode started with 5"):
        b.push(random_state(road, 6, 1, seed=0))
    with pytest.raises(ObservationError, match="out of range"):
        b.actor(np.array([7]), np.zeros((1, 2), np.int64), np.zeros(5, np.int64))
    with pytest.raises(ObservationError, match="action_memory"):
        b.actor(np.array([0]), np.zeros((2, 2), np.int64), np.zeros(5, np.int64))
    bad_lane = make_state(road, [10.0], [5], [1])
    with pytest.raises(ObservationError, match="lane 5"):
        b.reset(bad_lane)
    seg = {"kind": "multilane", "length_m": 100, "lanes": 2, "speed_limit_mps": 25.0}
    long_map = parse_map(
        {"name": "long", "lane_width_m": 3.2, "segments": [seg] * (MAX_SEGMENTS + 1)}
    )
    with pytest.raises(ObservationError, match="MAX_SEGMENTS"):
        ObservationBuilder(long_map, CFG, episode_steps=100)


# ---------------------------------------------------------------------------
# Both real backends through the same code path
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("backend_name", ["highway", "sumo"])
def test_observations_from_real_backends(road, backend_name):
    scenario = Scenario.with_cavs(25, 10)
    backend = make_backend(backend_name, road, SimConfig())
    try:
        state = backend.reset(scenario, seed=3).env(0)
        cav_index = np.flatnonzero(state.is_cav[0])
        assert cav_index.shape == (10,)
        b = ObservationBuilder(road, CFG, episode_steps=100)
        b.reset(state)
        rng = np.random.default_rng(0)
        refined = np.zeros(state.n_vehicles, np.int64)
        for step in range(6):
            obs = b.actor(cav_index, np.zeros((10, 2), np.int64), refined)
            crit = b.critic()
            check_layout(obs, crit, 10)
            assert np.array_equal(obs.alive, state.active[0][cav_index])
            assert crit.node_mask.sum() == state.active[0].sum()
            # At t = 0 vehicles start in rows close together: every alive CAV has neighbours.
            if step == 0:
                assert np.all(obs.hdv_mask.sum(1) + obs.cav_mask.sum(1) == K)
            cmd = CavCommands.idle(state.n_vehicles)
            cmd.speed_change_mps[0, cav_index] = rng.choice([-2.0, 0.0, 2.0], size=10)
            refined = rng.integers(0, 5, state.n_vehicles)
            state = backend.step(cmd).env(0)
            b.push(state)
        # After 6 pushes of a moving flow the ego history is a real trajectory.
        alive = obs.alive
        assert np.all(obs.ego_hist[alive][:, -1, DX] == 0.0)
        assert np.any(obs.ego_hist[alive][:, 0, DX] < 0.0)
    finally:
        backend.close()


@pytest.mark.parametrize("backend_name", ["highway", "sumo"])
def test_full_episode_on_real_backends_masks_cavs_that_left(backend_name):
    road = load_map("train-50")
    backend = make_backend(backend_name, road, SimConfig())
    try:
        state = backend.reset(Scenario.with_cavs(40, 16), seed=1).env(0)
        cav_index = np.flatnonzero(state.is_cav[0])
        b = ObservationBuilder(road, CFG, episode_steps=100)
        b.reset(state)
        saw_dead = False
        for _ in range(150):
            obs = b.actor(cav_index, np.zeros((16, 2), np.int64), np.zeros(40, np.int64))
            check_layout(obs, b.critic(), 16)
            dead = ~obs.alive
            if dead.any() and obs.alive.any():
                saw_dead = True
                assert np.all(obs.self_state[dead] == 0.0) and not obs.lane_mask[dead].any()
                # Nobody has a vehicle that left among its neighbours.
                idx, mask = b.neighbours
                assert np.all(state.active[0][idx[mask]])
            if not state.active[0].any():
                break
            cmd = CavCommands.idle(40)
            cmd.speed_change_mps[0, cav_index] = 2.0
            state = backend.step(cmd).env(0)
            b.push(state)
        assert saw_dead
    finally:
        backend.close()


def test_matched_horizon_options_keep_the_layout(road):
    """critic_step_input=False zeroes step/T; road_speed_limits puts limit/max in column 4."""
    import dataclasses

    from diacc.config import preset_road

    state = make_state(road, [100.0, 600.0], [0, 1], [1, 0], step=25)
    cfg = dataclasses.replace(CFG, critic_step_input=False, road_speed_limits=True)
    slow = preset_road(road, "paper-congestion")  # reduction segment at 15 m/s
    b, obs = build(slow, state, [0], cfg)
    crit = b.critic()
    assert crit.traffic[3] == 0.0 and crit.traffic[0] == pytest.approx(2 / 40)
    kinds = [seg.kind.startswith("reduction") for seg in slow.segments]
    expected = [15.0 / 25.0 if k else 1.0 for k in kinds]
    np.testing.assert_allclose(crit.road.reshape(MAX_SEGMENTS, 4)[:3, 3], expected, atol=1e-6)
    np.testing.assert_allclose(obs.road[0].reshape(MAX_SEGMENTS, 4)[:3, 3], expected, atol=1e-6)
    assert 15.0 / 25.0 in expected  # the preset lowered one segment
    check_layout(obs, crit, 1, cfg)


@pytest.mark.parametrize("compact", [False, True])
@pytest.mark.parametrize("step_input", [False, True])
@pytest.mark.parametrize("limits", [False, True])
def test_chosen_feature_functions_fill_every_field_once(road, compact, step_input, limits):
    """Whatever the options pick (features_for), the functions together fill each field of
    ActorObs and CriticState exactly once: none missing, none written twice."""
    import dataclasses

    from diacc.envs.observation import features_for

    cfg = dataclasses.replace(CFG, critic_step_input=step_input, road_speed_limits=limits)
    features = features_for(cfg, compact)
    b = ObservationBuilder(road, cfg, episode_steps=100, compact_critic=compact)
    state = random_state(road, 20, 6, seed=3)
    b.reset(state)
    frame = b._require_frame()
    from diacc.envs.observation.actor_features import Slots

    slots = Slots.of(  # the batch of one env: (1, C) slots
        state, np.arange(6)[None], np.zeros((1, 6, 2), np.int64), np.zeros((1, 20), np.int64)
    )
    for funcs, container, args in (
        (features.actor, ActorObs, (b._ctx, frame, slots)),
        (features.critic, CriticState, (b._ctx, frame)),
    ):
        written = [name for f in funcs for name in f(*args)]
        assert sorted(written) == sorted(f.name for f in dataclasses.fields(container))
    assert b.critic().traffic[3] == 0.0  # step 0 ...
    b.push(random_state(road, 20, 6, seed=4, step=7))  # ... a later step shows the clock
    assert (b.critic().traffic[3] > 0) == step_input


def test_a_feature_function_can_be_replaced(road):
    """ObservationBuilder(features=...) composes other functions of the same layout."""
    import dataclasses

    from diacc.envs.observation import features_for

    def no_traffic(ctx, frame):
        return {"traffic": np.zeros(frame.state.x_m.shape[:-1] + (4,), np.float32)}

    default = features_for(CFG)
    plugged = dataclasses.replace(default, critic=default.critic[:-1] + (no_traffic,))
    state = random_state(road, 20, 6, seed=5, step=30)
    ours, theirs = (ObservationBuilder(road, CFG, 100, features=f) for f in (default, plugged))
    for b in (ours, theirs):
        b.reset(state)
    assert ours.critic().traffic.any() and not theirs.critic().traffic.any()
    np.testing.assert_array_equal(ours.critic().nodes, theirs.critic().nodes)
