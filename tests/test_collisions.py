"""Collisions: what removes their causes on the demand road, and metrics they cannot flatter
(issue 57; docs/concepts/baselines.md, "Collisions")."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers import make_state

import diacc.sim.backends.sumo.worker as sumo_worker
from diacc.config import PSARConfig, RewardConfig, SimConfig
from diacc.envs.actions import ACCELERATE, LANE_RIGHT, REMAIN
from diacc.envs.env import BottleneckEnv, EnvConfig
from diacc.envs.episode import EpisodeDriver, play_episode
from diacc.envs.psar import CANCEL_LC, psar
from diacc.envs.vector import make_vector_env
from diacc.experiments.evalsettings import EvalSettings
from diacc.experiments.grid import Cell
from diacc.experiments.policies import build_policy, parse_policy
from diacc.sim.backends.sumo.backend import SumoBackend
from diacc.sim.backends.sumo.vtypes import cut_in_gap_terms
from diacc.sim.kinematics import safe_gap_m
from diacc.sim.maps import load_map
from diacc.sim.scenario import Scenario, draw_population

RELEASE = Cell(map="train-50", n_vehicles=25, cav_penetration=0.4, style_mix="D1")


# ------------------------------------------------------------------ SUMO: the HDVs' gap
@pytest.mark.parametrize("speed_mps", [0.0, 5.0, 13.9, 25.0, 33.0])
def test_sumo_hdvs_leave_a_commanded_cav_the_highway_backends_gap(speed_mps):
    """LC2013's gap in front of a CAV, ``minGap + v tau + v^2 / (2 b)`` at its present
    speed, equals the highway backend's: the CAV holds its commanded target (up to one
    ``speed_change_mps`` more) for a step, then brakes at ``safe_decel_mps2``."""
    sim = SimConfig()
    tau_s, min_gap_m = cut_in_gap_terms(sim)
    b = sim.cav.safe_decel_mps2
    sumo_m = min_gap_m + speed_mps * tau_s + speed_mps**2 / (2 * b)
    target_mps = speed_mps + sim.speed_change_mps
    highway_m = sim.cav.min_gap_m + safe_gap_m(target_mps, 0.0, sim.step_s, b)
    assert sumo_m == pytest.approx(float(highway_m))


def _entering_cavs_off_their_lane_centre(monkeypatch, mode: int) -> int:
    """CAVs of a SUMO demand episode seen, at the end of the step they entered, off their
    lane's centre line (a lane change of SUMO's own under way), with ``mode`` as the
    laneChangeMode of that step. No CAV has a command (each drives itself)."""
    monkeypatch.setattr(sumo_worker, "ENTERING_LANE_CHANGE_MODE", mode)
    road = load_map("train-50")
    scenario = Scenario(
        kind="demand", inflow_vph=4800, demand_s=60, warmup_s=0, cav_penetration=0.4
    )
    pop = draw_population(scenario, road, 7)
    backend = SumoBackend(road, SimConfig(episode_steps=60))
    sim = sumo_worker.SumoSim(backend._spec)
    try:
        state = sim.reset(7, pop)
        seen = state.active[0].copy()
        off_centre = 0
        for _ in range(60):
            state = sim.step(np.zeros(pop.n_vehicles, np.int16), np.full(pop.n_vehicles, np.nan))
            new = state.active[0] & ~seen & pop.is_cav
            drift = state.y_m[0] - road.lane_center_y_m(state.lane[0])
            off_centre += int(np.count_nonzero(new & (np.abs(drift) > 1e-6)))
            seen |= state.active[0]
    finally:
        sim.close()
    return off_centre


def test_a_cav_entering_on_sumo_keeps_its_lane_until_its_first_command(monkeypatch):
    """A change LC2013 began in the CAV's entry step went on after PSAR took over, unseen
    (the state showed the old lane): the CAV ran into the queue of the new lane."""
    assert (
        _entering_cavs_off_their_lane_centre(monkeypatch, sumo_worker.SUMO_DEFAULT_LANE_CHANGE_MODE)
        > 0
    )
    assert _entering_cavs_off_their_lane_centre(monkeypatch, 0) == 0


# ------------------------------------------------------------------ metrics
def _episode(backend: str, on_collision: str, steps: int = 60):
    """One release episode of CAVs that only accelerate, without PSAR (they collide)."""
    policy = build_policy(parse_policy("accelerate-nopsar"))
    settings = EvalSettings(backend, episode_steps=steps, on_collision=on_collision)
    driver = EpisodeDriver(policy, policy.env_config(RELEASE, settings))
    try:
        recorder = play_episode(driver, RELEASE.seed(0, "validation"))
        return driver.steps, recorder.summary(), driver.state, driver.env.batch.state.wrecked[0]
    finally:
        driver.close()


@pytest.mark.parametrize("backend", ["highway", "sumo"])
def test_a_crash_runs_on_to_the_horizon_and_cannot_shorten_the_delay(backend):
    """``remove`` (evaluation's rule): the wrecks leave the road, never arrived, and the
    episode runs to its horizon; its delay is at least that of the episode cut at the
    crash, which the cut one understated."""
    cut_steps, cut, _, _ = _episode(backend, "end")
    steps, full, state, wrecked = _episode(backend, "remove")
    assert cut_steps < 60 and cut.n_collisions >= 1
    assert steps == 60 and full.n_collisions >= cut.n_collisions
    assert wrecked.any() and not (state.active[0] & wrecked).any()
    assert not (state.arrived[0] & wrecked).any()
    assert full.delay_per_vehicle_s > cut.delay_per_vehicle_s


def test_evaluation_removes_wrecks_by_default_and_records_it():
    """Every evaluation names its rule in meta.json; training keeps ``end``."""
    settings = EvalSettings("highway")
    assert settings.on_collision == "remove"
    assert settings.describe()["settings"]["on_collision"] == "remove"
    assert settings.apply(SimConfig()).on_collision == "remove"
    assert SimConfig().on_collision == "end"
    assert (
        dataclasses.replace(settings, on_collision="end").apply(SimConfig()).on_collision == "end"
    )


def test_the_flow_figure_counts_the_crashed_episodes_it_marks():
    """The committed demand results before the fix: 4 of 10 SUMO heuristic episodes at
    4800 veh/h ended in a collision; the figure's point says so."""
    from diacc.experiments.flowplot import load_flow

    root = "benchmarks/studies/demand-training/results/flow-every-cav/sumo/heuristic"
    (point,) = [p for p in load_flow([root]) if p.inflow_vph == 4800]
    assert (point.crashed, point.episodes) == (4, 10)
    (calm,) = [p for p in load_flow([root]) if p.inflow_vph == 3600]
    assert calm.crashed == 0


def test_a_table_shows_the_collision_row_wherever_an_episode_crashed():
    from diacc.experiments.report.collect import build_table

    root = "benchmarks/studies/demand-training/results/flow-every-cav/sumo"
    crashed = build_table([f"{root}/heuristic/q3600", f"{root}/heuristic/q4800"], rows=("delay",))
    assert crashed.rows == ("delay", "collision")
    calm = build_table(
        [f"{root}/heuristic/q3600", f"{root}/release-3to1-s3/q3600"], rows=("delay",)
    )
    assert calm.rows == ("delay",)


# ------------------------------------------------------------------ PSAR: a human joining
def _right_from_lane_2(
    human_x_m: float, human_speed_mps: float, drift_m: float, cav_speed_mps: float = 0.0
):
    """PSAR for a CAV at x = 100 m in lane 2 asking to move right, one human in lane 0,
    ``drift_m`` off its centre line towards lane 1 (+: to the left)."""
    road = load_map("train-50")
    lane_m = road.lane_width_m
    y_m = [2.5 * lane_m, 0.5 * lane_m + drift_m]
    state = make_state(
        [100.0, human_x_m],
        [2, 0],
        [cav_speed_mps, human_speed_mps],
        is_cav=[True, False],
        y_m=y_m,
    )
    res = psar(state, np.array([[0]]), np.array([[LANE_RIGHT]]), PSARConfig(), road)
    return int(res.action[0, 0]), int(res.rule[0, 0])


def test_a_human_already_moving_into_the_target_lane_behind_cancels_the_change():
    """SUMO, 3600 veh/h: a standing CAV moved right into lane 1 while a human 12 m back at
    18 m/s, half-way over from lane 0, moved into it too; they collided. A vehicle whose
    change into the target lane is under way is one of that lane's rear vehicles."""
    assert _right_from_lane_2(83.3, 18.0, drift_m=0.8) == (REMAIN, CANCEL_LC)
    # on its centre line it is nobody's rear vehicle (checking every human two lanes over
    # cost 10-15 s of delay per vehicle on SUMO at 4800 veh/h: docs/concepts/psar.md)
    assert _right_from_lane_2(83.3, 18.0, drift_m=0.0)[0] == LANE_RIGHT
    # moving away from the target lane, neither
    assert _right_from_lane_2(83.3, 18.0, drift_m=-0.8)[0] == LANE_RIGHT
    # nor when it is far enough back to brake for the CAV
    assert _right_from_lane_2(-200.0, 18.0, drift_m=0.8)[0] == LANE_RIGHT


def test_a_human_already_moving_into_the_target_lane_ahead_cancels_the_change():
    """SUMO, 4800 veh/h (issue 60, a suite-trained agent): a CAV at 10.5 m/s moved right
    into lane 1 while a standing human 10 m ahead, 1 m over from lane 0, moved into it
    too; they collided. Such a vehicle is one of the target lane's front vehicles."""
    ahead = dict(human_x_m=115.0, human_speed_mps=0.1, cav_speed_mps=10.5)
    assert _right_from_lane_2(**ahead, drift_m=1.0) == (REMAIN, CANCEL_LC)
    assert _right_from_lane_2(**ahead, drift_m=0.0)[0] == LANE_RIGHT  # on its centre line
    assert _right_from_lane_2(**ahead, drift_m=-1.0)[0] == LANE_RIGHT  # moving away
    far = dict(ahead, human_x_m=400.0)
    assert _right_from_lane_2(**far, drift_m=1.0)[0] == LANE_RIGHT  # far enough ahead


# ------------------------------------------------------------------ the demand road
def _demand_collisions(backend: str, inflow_vph: float, episode: int, steps: int) -> int:
    """Collisions of the heuristic's `test` episode on the demand road of issue 57
    (train-50, 480 s, 120 s warm-up, rho 0.4, D1, every CAV an agent, PSAR headway/known)."""
    cell = Cell(
        map="train-50",
        n_vehicles=25,
        cav_penetration=0.4,
        style_mix="D1",
        inflow_vph=inflow_vph,
        demand_s=480,
        warmup_s=120,
    )
    settings = EvalSettings(
        backend,
        episode_steps=steps,
        style_preset="realistic",
        psar_horizon="headway",
        psar_full_brake="known",
        agent_slots="every",
    )
    policy = build_policy(parse_policy("heuristic"))
    driver = EpisodeDriver(policy, policy.env_config(cell, settings))
    try:
        return play_episode(driver, cell.seed(episode, "test")).summary().n_collisions
    finally:
        driver.close()


@pytest.mark.parametrize(
    ("inflow_vph", "episode", "steps"),
    [(4800, 7, 180), (3600, 2, 176)],  # a CAV's entry; a human joining from the lane beyond
)
def test_the_heuristic_no_longer_crashes_where_it_did_on_sumo(inflow_vph, episode, steps):
    """Two of the collisions issue 57 found, each replayed to just past its step (178,
    174): entering CAVs keep their lane, and PSAR sees a human joining the target lane."""
    assert _demand_collisions("sumo", inflow_vph, episode, steps) == 0


@pytest.mark.slow
@pytest.mark.parametrize("backend", ["highway", "sumo"])
def test_no_collision_with_psar_far_above_capacity(backend):
    """4800 veh/h, three full `test` episodes (benchmarks/studies/safety/demand-collisions
    measures 10 per inflow from 1600 to 4800)."""
    assert [_demand_collisions(backend, 4800, e, 480) for e in range(3)] == [0, 0, 0]


# ------------------------------------------------------------------ training with "remove"
def _first_crash(on_collision: str, reward: RewardConfig | None = None):
    """Every CAV accelerating without PSAR on the training cell until the first crash."""
    config = EnvConfig(
        map="train-50",
        use_psar=False,
        scenario=Scenario(n_vehicles=25, cav_penetration=0.4),
        sim=SimConfig(on_collision=on_collision),
        reward=reward or RewardConfig(),
    )
    envs = make_vector_env(config, 1, 3, "sync")
    try:
        envs.reset(first_episode=0)
        for step in range(60):
            out = envs.step(np.full((1, envs.n_cavs), ACCELERATE))
            if (out.terms.collision < 0).any():
                return step, out
    finally:
        envs.close()
    raise AssertionError("no CAV crashed in 60 accelerating steps")


def test_a_crash_costs_the_team_the_same_whether_the_wreck_stays_or_is_removed():
    """Under ``remove`` (per-CAV termination, a training option) the wreck is off the road
    when the reward is scored; its collision term must still count, exactly as under
    ``end``, where the wreck stays (before the fix it was masked out: crashing was free)."""
    end_step, end = _first_crash("end")
    step, removed = _first_crash("remove")
    assert step == end_step and end.terminated[0] and not removed.terminated[0]
    np.testing.assert_array_equal(removed.terms.collision, end.terms.collision)
    np.testing.assert_array_equal(removed.alive, end.alive)
    np.testing.assert_allclose(removed.team.total, end.team.total)
    crashed = removed.terms.collision[0] < 0
    assert crashed.any() and not removed.actor_obs.alive[0][crashed].any()


def test_a_removed_wreck_ends_its_agent_in_the_pettingzoo_env_at_once():
    config = EnvConfig(
        map="train-50",
        use_psar=False,
        scenario=Scenario(n_vehicles=25, cav_penetration=0.4),
        sim=SimConfig(on_collision="remove"),
    )
    env = BottleneckEnv(config)
    try:
        env.reset(seed=3)
        for _ in range(60):
            acting = list(env.agents)
            _, _, terms, truncs, infos = env.step({a: ACCELERATE for a in acting})
            if any(terms.values()):
                break
        ended = [a for a in acting if terms[a]]
        assert ended and all(len(infos[a]["collisions"]) for a in ended)
        assert not set(ended) & set(env.agents) and env.agents, "the others drive on"
    finally:
        env.close()


def test_the_crash_penalty_charges_each_crashing_cav_outside_the_softmin():
    """``env.reward.crash_penalty``: r_done loses the penalty once per CAV that crashed."""
    _, plain = _first_crash("remove")
    _, charged = _first_crash("remove", RewardConfig(crash_penalty=50.0))
    n_crashed = int((plain.terms.collision[0] < 0).sum())
    assert n_crashed >= 1
    np.testing.assert_allclose(
        charged.terms.completion - plain.terms.completion, [-50.0 * n_crashed]
    )
    np.testing.assert_allclose(charged.team.total - plain.team.total, [-50.0 * n_crashed])
