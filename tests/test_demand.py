"""The ``demand`` scenario kind: seeded arrivals on both backends, agent slots that refill."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from helpers import SHORT_MAP
from pettingzoo.test import parallel_api_test

from diacc.config import ConfigError, EnvConfig, SimConfig, TrainConfig, override
from diacc.envs.actions import LANE_RIGHT
from diacc.envs.env import BottleneckEnv
from diacc.envs.episode import EpisodeDriver, play_episode
from diacc.envs.vector import make_vector_env
from diacc.experiments.policies import ScriptedPolicy
from diacc.learn.mappo import make_agent, seed_everything, train
from diacc.learn.models.inputs import to_tensors
from diacc.learn.ppo import collect_rollout
from diacc.sim.backends.base import CavCommands, make_backend
from diacc.sim.maps import parse_map
from diacc.sim.scenario import Demand, Scenario, draw_population
from diacc.sim.state import TrafficState

BACKENDS = ["highway", "sumo"]

STRAIGHT_MAP = """
name = "straight"
lane_width_m = 3.2
[[segments]]
kind = "multilane"
length_m = 600
lanes = 3
speed_limit_mps = 25.0
"""

#: 20 vehicles enter over 20 s (half CAVs, at most 3 driven at once) on a 160 m road.
DEMAND = Scenario(kind="demand", inflow_vph=3600, demand_s=20, cav_penetration=0.5, cav_slots=3)


@pytest.fixture
def short_map(tmp_path):
    path = tmp_path / "short.toml"
    path.write_text(SHORT_MAP)
    return str(path)


def _config(backend: str, road: str, **sim) -> EnvConfig:
    return EnvConfig(
        backend=backend, map=road, scenario=DEMAND, sim=SimConfig(episode_steps=40, **sim)
    )


def test_arrival_sequence_is_seeded_and_regular():
    road = parse_map({"name": "m", "lane_width_m": 3.2, "segments": [
        {"kind": "multilane", "length_m": 500, "lanes": 4, "speed_limit_mps": 25.0}]})  # fmt: skip
    scenario = Scenario(kind="demand", inflow_vph=2400, demand_s=300, cav_penetration=0.4)
    a, b = draw_population(scenario, road, 7), draw_population(scenario, road, 7)
    other = draw_population(scenario, road, 8)
    for name in ("is_cav", "style", "x_m", "lane", "speed_mps", "depart_s"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.array_equal(a.depart_s, other.depart_s)
    assert a.n_vehicles == 200 and a.is_cav.sum() == 80
    headway_s = 3600 / 2400
    k = np.arange(200)
    assert np.all((a.depart_s >= k * headway_s) & (a.depart_s < (k + 1) * headway_s))


def test_both_backends_replay_the_same_arrivals(tmp_path):
    """Same vehicles, in the same order, lanes and styles; entry within one step."""
    road = tmp_path / "straight.toml"
    road.write_text(STRAIGHT_MAP)
    scenario = Scenario(kind="demand", inflow_vph=900, demand_s=40, cav_penetration=0.0)
    entered = {}
    for backend in BACKENDS:
        env = BottleneckEnv(EnvConfig(backend=backend, map=str(road)))  # the map with its preset
        sim = make_backend(backend, env.road, env.config.sim)
        env.close()
        state = sim.reset(scenario, 5).env(0)
        first = np.full(state.n_vehicles, -1)
        lane = np.full(state.n_vehicles, -1)
        for t in range(45):
            state = sim.step(CavCommands.idle(state.n_vehicles)).env(0)
            new = state.active[0] & (first < 0)  # state: a batch of one env
            first[new], lane[new] = t, state.lane[0][new]
        sim.close()
        entered[backend] = (first, lane, state.style[0].copy())
    (f_h, l_h, s_h), (f_s, l_s, s_s) = entered["highway"], entered["sumo"]
    assert (f_h >= 0).all() and (f_s >= 0).all()
    assert np.abs(f_h - f_s).max() <= 1
    np.testing.assert_array_equal(l_h, l_s)
    np.testing.assert_array_equal(s_h, s_s)
    assert np.all(np.diff(f_h) >= 0)  # in order of the sequence


def _slot_episode(backend: str, road: str, seed: int = 3):
    env = BottleneckEnv(_config(backend, road))
    env.reset_arrays(seed)
    occupants, refills, served = [env.slot_vehicle.copy()], [env.slot_start.copy()], set()
    try:
        while True:
            out = env.step_arrays(np.full(env.n_cavs, LANE_RIGHT))  # out of the ending lane
            occupants.append(env.slot_vehicle.copy())
            refills.append(out.slot_start)
            served |= set(env.slot_vehicle[env.slot_vehicle >= 0].tolist())
            assert np.array_equal(out.alive, out.state.active[0, env.cav_index])
            if out.terminated or out.truncated:
                return env, np.array(occupants), np.array(refills), served, out
    finally:
        env.close()


@pytest.mark.parametrize("backend", BACKENDS)
def test_slots_refill_as_cavs_enter_and_leave(backend, short_map):
    env, occupants, refills, served, out = _slot_episode(backend, short_map)
    assert env.n_cavs == 3 and len(env.possible_agents) == 10
    # Slots got several CAVs over the episode, each flagged when it came.
    changes = (occupants[1:] != occupants[:-1]) & (occupants[1:] >= 0)
    np.testing.assert_array_equal(changes, refills[1:])
    assert refills.sum() >= 2 * env.n_cavs and refills.sum(axis=0).max() >= 2
    assert len(served) >= 8  # of 10 CAVs (one may pass while the slots are full)
    # A slot holds one CAV at a time and a CAV one slot.
    for row in occupants:
        held = row[row >= 0]
        assert len(set(held.tolist())) == len(held)


@pytest.mark.parametrize("backend", BACKENDS)
def test_parallel_api_with_agents_entering_and_leaving(backend, short_map):
    env = BottleneckEnv(_config(backend, short_map))
    try:
        parallel_api_test(env, num_cycles=40)
        env.reset(seed=3)
        seen, left = set(env.agents), set()
        for _ in range(40):
            acting = set(env.agents)
            _, _, terms, truncs, _ = env.step({a: 0 for a in env.agents})
            left |= {a for a in acting if terms[a] or truncs[a]}
            seen |= set(env.agents)
            if not env.agents and left:
                break
        assert len(seen) > env.n_cavs and left  # more CAVs than slots came, some left
        assert set(env.possible_agents) >= seen
    finally:
        env.close()


def test_refilled_slot_acts_from_a_fresh_recurrent_state(tmp_path, short_map):
    cfg = override(
        TrainConfig(),
        {"n_envs": 1, "rollout_steps": 40, "chunk_len": 10, "device": "cpu",
         "env.map": short_map, "env.sim.episode_steps": 40, "model.hidden_dim": 32,
         "model.gru_hidden": 32, "model.cross_dim": 32, "run_dir": str(tmp_path / "run")},
    )  # fmt: skip
    cfg = override(cfg, {"env.scenario": DEMAND})
    seed_everything(cfg.seed)
    agent = make_agent(cfg, torch.device("cpu"))
    envs = make_vector_env(cfg.env, cfg.n_envs, cfg.seed)
    try:
        roll, _, _ = collect_rollout(agent, envs, cfg, 0, global_step=0)
    finally:
        envs.close()
    refill = roll.agent_start & ~roll.episode_start[:, :, None]  # (S, E, C)
    assert refill.any()
    t, e, c = (int(i) for i in np.argwhere(refill)[0])
    assert roll.actor_hidden[t, e, c].any()  # the previous occupant's state is there...
    obs = to_tensors(roll.actor_obs[t].unbatched(e))
    actor = agent.rollout_actor
    with torch.no_grad():
        start = torch.as_tensor(roll.agent_start[t, e])
        logits, _ = actor(obs, torch.as_tensor(roll.actor_hidden[t, e]), start)
        fresh, _ = actor(obs, torch.zeros_like(torch.as_tensor(roll.actor_hidden[t, e])), start)
    torch.testing.assert_close(logits[c], fresh[c])  # ...and is not used


def tiny_demand_run(tmp_path, road: str, scenario: Scenario, steps: int, updates: int, **settings):
    """Train a tiny agent on ``scenario`` (2 envs, ``steps``-step episodes, ``updates``
    updates, config ``settings`` on top) and play its checkpoint for one episode: the
    episode's metrics."""
    cfg = override(
        TrainConfig(),
        {"n_envs": 2, "rollout_steps": steps, "chunk_len": 10, "total_steps": updates * 2 * steps,
         "epochs": 1, "device": "cpu", "env.map": road, "env.sim.episode_steps": steps,
         "model.hidden_dim": 32, "model.gru_hidden": 32, "model.cross_dim": 32,
         "run_dir": str(tmp_path / "run"), **settings},
    )  # fmt: skip
    cfg = override(cfg, {"env.scenario": scenario})
    train(cfg, progress=False)
    from diacc.experiments.policies import CheckpointPolicy

    policy = CheckpointPolicy(tmp_path / "run" / "checkpoint.pt")
    driver = EpisodeDriver(policy, cfg.env)
    try:
        return play_episode(driver, 11).summary()
    finally:
        driver.close()


@pytest.mark.parametrize("backend", BACKENDS)
def test_tiny_training_and_evaluation_run(backend, tmp_path, short_map):
    metrics = tiny_demand_run(tmp_path, short_map, DEMAND, 40, 2, **{"env.backend": backend})
    assert metrics.n_vehicles > 0 and np.isfinite(metrics.mean_speed_mps)


def test_warmup_is_not_measured(short_map):
    config = EnvConfig(
        map=short_map,
        scenario=Scenario(kind="demand", inflow_vph=3600, demand_s=20, warmup_s=19, cav_slots=3),
        sim=SimConfig(episode_steps=30),
    )
    driver = EpisodeDriver(ScriptedPolicy("remain"), config)
    try:
        recorder = play_episode(driver, 2)
    finally:
        driver.close()
    assert recorder.speed_samples().time_s.min() >= 19.0
    assert 0 < recorder.summary().n_vehicles < 20  # those on the road after the warm-up


def test_episode_that_ends_in_the_warmup_has_an_empty_summary():
    """A collision may end a training episode before the warm-up: nothing is measured."""
    from helpers import make_state

    from diacc.config import preset_road
    from diacc.envs.metrics import EpisodeRecorder
    from diacc.sim.maps import load_map

    recorder = EpisodeRecorder(preset_road(load_map("train-50"), "realistic"), warmup_s=10.0)
    recorder.record(
        TrafficState.concat([make_state([50, 10], [0, 1], segment=[0, 0], time_s=5, step=5)])
    )
    summary = recorder.summary()
    assert summary.n_vehicles == 0 and math.isnan(summary.mean_speed_mps)
    assert len(recorder.speed_samples().speed_mps) == 0


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"inflow_vph": -100}, "'inflow_vph' must be in"),
        ({"inflow_vph": 50_000}, "'inflow_vph' must be in"),
        ({"demand_s": 0}, "'demand_s' must be > 0"),
        ({"warmup_s": 400, "demand_s": 300}, "longer than warmup_s"),
        ({"cav_slots": 0}, "'cav_slots' must be"),
        ({"warmup_s": -1}, "'warmup_s' must be >= 0"),
    ],
)
def test_bad_demand_values_are_one_line_errors(kwargs, match):
    with pytest.raises(ConfigError, match=match) as err:
        Scenario(kind="demand", **kwargs)
    assert "\n" not in str(err.value)


def test_warmup_longer_than_the_episode_is_an_error():
    with pytest.raises(ConfigError, match="not shorter than the episode"):
        EnvConfig(scenario=Scenario(kind="demand", warmup_s=200), sim=SimConfig(episode_steps=100))
    with pytest.raises(ConfigError, match="'kind' must be one of release, demand, got 'flood'"):
        Scenario(kind="flood")


def test_grid_sweeps_inflow(tmp_path):
    from diacc.experiments.grid import GridError, load_grid

    grid = tmp_path / "demand.toml"
    grid.write_text(
        '[product]\nmap = ["train-50"]\ninflow_vph = [1600, 3600]\ncav_penetration = [0.4]\n'
    )
    cells = load_grid(grid)
    assert [c.inflow_vph for c in cells] == [1600.0, 3600.0]
    assert cells[0].key == "train-50_Q1600_rho0.40_D1"
    base = Scenario(kind="demand", demand_s=600, warmup_s=120, cav_slots=8)
    scenario = cells[1].scenario(base=base)
    # The cell fixes the traffic (default timing for every policy, so a demand-trained
    # checkpoint meets the references' traffic); the agent slots are the policy's.
    default = Demand()
    n_default = int(3600 * default.demand_s / 3600)
    assert (scenario.kind, scenario.inflow_vph, scenario.n_vehicles) == ("demand", 3600, n_default)
    assert (scenario.demand_s, scenario.warmup_s) == (default.demand_s, default.warmup_s)
    assert scenario.cav_slots == 8
    assert cells[1].scenario().n_vehicles == n_default
    grid.write_text('[product]\nmap = ["train-50"]\ninflow_vph = [3600]\ndemand_s = [480]\n'
                    'warmup_s = [120]\n')  # fmt: skip
    (timed,) = load_grid(grid)
    assert (timed.n_vehicles, timed.demand_s, timed.warmup_s) == (480, 480.0, 120.0)
    assert timed.key == cells[1].key  # same seeds at any timing
    scenario = timed.scenario(base=base)
    assert (scenario.n_vehicles, scenario.demand_s, scenario.warmup_s) == (480, 480, 120)
    grid.write_text('[[cells]]\nmap = "train-50"\nn_vehicles = 25\ndemand_s = 480\n'
                    'cav_penetration = 0.4\nstyle_mix = "D1"\n')  # fmt: skip
    with pytest.raises(GridError, match="demand_s needs inflow_vph"):
        load_grid(grid)
    assert load_grid("train")[0].inflow_vph == 0.0  # the paper's cells stay releases
    grid.write_text('[[cells]]\nmap = "train-50"\ninflow_vph = -5\ncav_penetration = 0.4\n'
                    'style_mix = "D1"\n')  # fmt: skip
    with pytest.raises(GridError, match="inflow_vph must be a positive number"):
        load_grid(grid)
    grid.write_text('[[cells]]\nmap = "train-50"\ninflow_vph = 90000\ncav_penetration = 0.4\n'
                    'style_mix = "D1"\n')  # fmt: skip
    with pytest.raises(GridError, match="'inflow_vph' must be in"):
        load_grid(grid)


@pytest.mark.parametrize(
    "settings, match",
    [
        (["env.scenario.inflow_vph=-5"], "'env.scenario.inflow_vph' must be in"),
        (["env.scenario.inflow_vph=1e6"], "'env.scenario.inflow_vph' must be in"),
        (["env.scenario.warmup_s=500"], "longer than warmup_s"),
        (["env.scenario.demand_s=600", "env.scenario.warmup_s=200"], "not shorter than the"),
    ],
)
def test_cli_bad_demand_is_a_one_line_error(tmp_path, capsys, settings, match):
    from diacc.cli import main

    argv = ["train", "--run-dir", str(tmp_path / "run"), "--no-progress"]
    for setting in ["env.scenario.kind=demand", *settings]:
        argv += ["--set", setting]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("diacc: error: ") and "\n" not in err and match in err, err


def test_flows_count_the_window_after_the_warm_up():
    """Vehicle 0 passed the bottleneck during the warm-up; vehicle 2 enters after it."""
    from helpers import make_state

    from diacc.config import preset_road
    from diacc.envs.metrics import EpisodeRecorder
    from diacc.sim.maps import load_map

    road = preset_road(load_map("train-50"), "realistic")  # reduction ends at 800 m
    recorder = EpisodeRecorder(road, warmup_s=10.0)
    pending = dict(active=[True, True, False], speed_mps=25.0)
    recorder.record(
        TrafficState.concat([make_state([850, 700, 10], [0, 0, 1], segment=[2, 1, 0], **pending)])
    )
    recorder.record(
        TrafficState.concat(
            [
                make_state(
                    [900, 790, 10], [0, 0, 1], segment=[2, 1, 0], time_s=10, step=10, **pending
                )
            ]
        )
    )
    recorder.record(
        TrafficState.concat(
            [make_state([950, 810, 60], [0, 0, 1], segment=[2, 2, 0], time_s=20, step=20)]
        )
    )
    m = recorder.summary()
    assert m.throughput_vph == pytest.approx(3600.0 / 10.0)  # vehicle 1 alone, in 10 s
    assert m.n_vehicles == 3
    # Delay inside the window (from t = 10): 10 s minus 50 m and 20 m at 25 m/s for
    # vehicles 0 and 1; vehicle 2 entered at t = 20, the window's last state.
    assert m.total_delay_s == pytest.approx((10 - 50 / 25) + (10 - 20 / 25))
    assert math.isnan(m.mean_travel_time_s)  # nobody entered after the warm-up and arrived


def test_diacc_train_on_demand_through_the_cli(tmp_path, capsys):
    """A few steps of demand training as users start it (issue 61: the config table
    printer had no default for the demand keys and ended in a KeyError)."""
    from diacc.cli import main

    run = tmp_path / "run"
    argv = ["train", "--steps", "40", "--envs", "2", "--out", str(run), "--no-progress"]
    for setting in ("rollout_steps=20", "env.sim.episode_steps=20"):
        argv += ["--set", setting]
    argv += ["--set", "env.scenario.kind=demand", "--set", "env.scenario.inflow_vph=1800"]
    assert main(argv) == 0
    table = capsys.readouterr().out
    assert "env.scenario.inflow_vph" in table and "'demand'" in table  # the changed keys
    assert (run / "checkpoint.pt").exists()
