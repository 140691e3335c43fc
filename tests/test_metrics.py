"""Tests of diacc.envs.metrics on a hand-built three-step episode."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest
from helpers import make_state

from diacc.envs.metrics import EpisodeRecorder, MetricsError
from diacc.envs.psar import PSARResult
from diacc.sim.maps import load_map
from diacc.sim.state import TrafficState

ROAD = load_map("train-25")  # segments: multilane 0-500, reduction25 500-800, multilane
CAV = [True, True, False, False]
LANE = [0, 1, 2, 3]


def episode() -> list:
    """Vehicles 0, 1 CAVs, 2, 3 HDVs, each in its own lane (no gap/TTC events)."""
    s0 = make_state(
        [100.0, 550.0, 200.0, 1290.0],
        LANE,
        [10.0, 20.0, 2.0, 24.0],
        is_cav=CAV,
        segment=[0, 1, 0, 2],
        time_s=0.0,
        step=0,
    )
    s1 = make_state(
        [111.0, 569.0, 203.0, 1314.0],
        LANE,
        [12.0, 18.0, 4.0, 24.0],
        is_cav=CAV,
        segment=[0, 1, 0, 2],
        time_s=1.0,
        step=1,
        active=[True, True, True, False],
        arrived=[False, False, False, True],
        arrivals=[3],
        collisions=[(1, 2)],
    )
    s2 = make_state(
        [124.0, 588.0, 206.0, 1314.0],
        LANE,
        [14.0, 20.0, 2.5, 24.0],
        is_cav=CAV,
        segment=[0, 1, 0, 2],
        time_s=2.0,
        step=2,
        accel_mps2=[-5.0, 0, 0, 0],
        active=[True, True, True, False],
        arrived=[False, False, False, True],
        collisions=[(2, 1)],
    )
    return [s0, s1, s2]


def one(state: TrafficState) -> TrafficState:
    """One env's state as the batch of one a recorder takes."""
    return TrafficState.concat([state])


def psar_result(mask: list[int]) -> PSARResult:
    """One env's PSAR result as a batch of one, (1, C)."""
    n = len(mask)
    return PSARResult(
        action=np.zeros((1, n), np.int64),
        speed_change_mps=np.zeros((1, n)),
        rule=np.zeros((1, n), np.int8),
        rule_mask=np.array([mask], np.int8),
        decel_lc_mps2=np.zeros((1, n)),
        invalid_lc=np.zeros((1, n), bool),
        active=np.ones((1, n), bool),
    )


def recorded() -> EpisodeRecorder:
    rec = EpisodeRecorder(ROAD)
    s0, s1, s2 = episode()
    rec.record(one(s0))
    rec.record(one(s1), psar_result([0b0001, 0]))  # Cancel-LC
    rec.record(one(s2), psar_result([0b0101, 0b1000]))  # Cancel-LC + Force-Brake, Suppr-Accel
    return rec


def test_summary_matches_hand_computation():
    m = recorded().summary()
    # samples: t0 10 20 2 24 | t1 12 18 4 | t2 14 20 2.5 (vehicle 3 left after t0)
    assert m.mean_speed_mps == pytest.approx(126.5 / 10)
    var = sum(v * v for v in [10, 20, 2, 24, 12, 18, 4, 14, 20, 2.5]) / 10 - (126.5 / 10) ** 2
    assert m.std_speed_mps == pytest.approx(math.sqrt(var))  # 7.8027
    assert m.mean_cav_speed_mps == pytest.approx(94.0 / 6)
    assert m.mean_hdv_speed_mps == pytest.approx(32.5 / 4)
    assert m.mean_speed_by_kind_mps["multilane"] == pytest.approx(68.5 / 7)
    assert m.mean_speed_by_kind_mps["reduction25"] == pytest.approx(58.0 / 3)
    assert math.isnan(m.mean_speed_by_kind_mps["reduction50"])
    assert m.p_we == pytest.approx(1 / 4)  # vehicle 2 (2 and 2.5 m/s < 3)
    assert m.p_sce == pytest.approx(3 / 4)  # 0 emergency braking, 1 and 2 collision
    assert m.n_collisions == 1  # the same pair on two steps
    assert m.arrived_fraction == pytest.approx(1 / 4)
    assert m.mean_travel_time_s == pytest.approx(1.0)
    assert m.episode_steps == 2
    assert m.n_vehicles == 4
    assert m.psar_decisions == 4
    assert m.psar_fire_rate == pytest.approx(
        {"cancel_lc": 0.5, "decel_lc": 0.0, "force_brake": 0.25, "suppr_accel": 0.25}
    )


def test_speed_samples_export_rows_and_csv(tmp_path):
    samples = recorded().speed_samples()
    rows = samples.rows()
    assert len(rows) == 10
    assert rows[0] == (0, 0, 0.0, 10.0, "multilane", True)
    assert rows[1] == (1, 0, 0.0, 20.0, "reduction25", True)
    assert rows[-1] == (2, 2, 2.0, 2.5, "multilane", False)
    path = tmp_path / "speeds.csv"
    samples.to_csv(path)
    with open(path) as fh:
        table = list(csv.reader(fh))
    assert table[0] == list(samples.COLUMNS)
    assert len(table) == 11 and table[4][4] == "multilane"


def test_recorder_rejects_inconsistent_input():
    rec = EpisodeRecorder(ROAD)
    with pytest.raises(MetricsError, match="no state"):
        rec.summary()
    rec.record(one(make_state([0.0, 10.0], [0, 1])))
    with pytest.raises(MetricsError, match="vehicles"):
        rec.record(one(make_state([0.0], [0])))


def test_flow_metrics_match_hand_computation():
    recorder = EpisodeRecorder(ROAD)
    for state in episode():
        recorder.record(one(state))
    m = recorder.summary()
    # Only vehicle 3 is past the reduction's end (800 m): 1 vehicle in 2 s.
    assert m.throughput_vph == pytest.approx(1800.0)
    # Time on the road minus distance / 25 m/s: 2 - 24/25, 2 - 38/25, 2 - 6/25, and
    # vehicle 3 arrived at t = 1 after the 10 m to the route end (1300 m).
    delays = [2 - 24 / 25, 2 - 38 / 25, 2 - 6 / 25, 1 - 10 / 25]
    assert m.total_delay_s == pytest.approx(sum(delays))
    assert m.delay_per_vehicle_s == pytest.approx(sum(delays) / 4)
    assert m.mean_arrived_speed_mps == pytest.approx(24.0)  # vehicle 3's one sample
    assert m.never_arrived_fraction == pytest.approx(0.75)


def test_delay_uses_each_segments_limit():
    from diacc.config import preset_road

    road = preset_road(load_map("train-50"), "paper-congestion")  # reduction at 15 m/s
    recorder = EpisodeRecorder(road)
    recorder.record(one(make_state([450.0], [0], 20.0, segment=0, time_s=0.0, step=0)))
    recorder.record(one(make_state([850.0], [0], 20.0, segment=2, time_s=30.0, step=30)))
    m = recorder.summary()
    # free flow 450 -> 850 m: 50 / 25 + 300 / 15 + 50 / 25 = 24 s; still on the road at t = 30
    assert m.total_delay_s == pytest.approx(6.0)
    assert m.throughput_vph == pytest.approx(3600.0 / 30.0)
    assert math.isnan(m.mean_arrived_speed_mps) and m.never_arrived_fraction == 1.0


def test_a_batch_recorder_equals_one_recorder_per_env_with_episodes_out_of_step():
    """E episodes side by side, one restarted mid-way, with a warm-up: each row's
    summary and speed samples are those of a recorder fed that env's states alone."""
    from diacc.config import EnvConfig, override
    from diacc.envs.batch import EnvBatch, Simulators
    from diacc.sim.backends.base import make_backend

    cfg = override(
        EnvConfig(),
        {"map": "train-25", "sim.episode_steps": 40, "scenario.n_vehicles": 12},
    )
    sims = Simulators([make_backend("highway", ROAD, cfg.sim) for _ in range(3)])
    batch = EnvBatch(cfg, sims)
    rng = np.random.default_rng(0)
    batch.reset(np.arange(3), [11, 12, 13])
    together = EpisodeRecorder(ROAD, cfg.events, warmup_s=3.0, n_envs=3)
    alone = [EpisodeRecorder(ROAD, cfg.events, warmup_s=3.0) for _ in range(3)]
    together.record(batch.state.traffic)
    for e in range(3):
        alone[e].record(batch.state.traffic.env(e))
    finished = []
    for t in range(30):
        out = batch.step(rng.integers(0, 5, (3, batch.n_cavs)))
        together.record(out.state, psar=out.psar, critical=out.critical)
        for e in range(3):
            alone[e].record(out.state.env(e), psar=out.psar.env(e))
        if t == 12:  # env 1 starts its next episode; the others go on
            finished.append((together.summary(1), alone[1].summary()))
            batch.reset(np.array([1]), [21])
            together.start(np.array([1]))
            together.record(batch.state.traffic, rows=np.array([False, True, False]))
            alone[1] = EpisodeRecorder(ROAD, cfg.events, warmup_s=3.0)
            alone[1].record(batch.state.traffic.env(1))
    finished += [(together.summary(e), alone[e].summary()) for e in range(3)]
    for mine, theirs in finished:
        assert repr(mine.as_dict()) == repr(theirs.as_dict())
    for e in range(3):
        for name, column in vars(together.speed_samples(e)).items():
            np.testing.assert_array_equal(column, getattr(alone[e].speed_samples(), name), name)
    assert together.speed_samples(1).step.min() == 3  # the new episode's, from the warm-up on
