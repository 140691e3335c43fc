"""Baselines that isolate control: same-mix (CAV slots driven by humans) and the heuristic."""

from __future__ import annotations

import numpy as np
import pytest

from diacc.config import CAV_STYLE, NORMAL, STYLE_NAMES, ConfigError
from diacc.envs.actions import ACCELERATE, LANE_LEFT, LANE_RIGHT
from diacc.envs.episode import EpisodeDriver
from diacc.envs.observation import ActorObs
from diacc.experiments.evaluate import run_episode
from diacc.experiments.grid import Cell
from diacc.experiments.policies import (
    HEURISTIC_LEAVE_M,
    EvalSettings,
    PolicyError,
    PolicySpec,
    PureHdvPolicy,
    SameMixPolicy,
    build_policy,
    heuristic_actions,
    parse_policy,
)
from diacc.sim.maps import load_map
from diacc.sim.scenario import Scenario, draw_population

CELL = Cell("train-50", 20, 0.4, "D1")


def test_same_mix_keeps_the_draw_and_hands_the_slots_to_humans():
    road = load_map("train-50")
    cavs = draw_population(Scenario(n_vehicles=20, cav_penetration=0.4), road, seed=5)
    for style in STYLE_NAMES:
        humans = draw_population(
            Scenario(n_vehicles=20, cav_penetration=0.4, cav_slot_style=style), road, seed=5
        )
        assert not humans.is_cav.any()
        assert np.all(humans.style[cavs.is_cav] == STYLE_NAMES.index(style))
        assert np.array_equal(humans.style[~cavs.is_cav], cavs.style[~cavs.is_cav])
        assert np.array_equal(humans.x_m, cavs.x_m) and np.array_equal(humans.lane, cavs.lane)
    assert np.all(cavs.style[cavs.is_cav] == CAV_STYLE)
    assert Scenario(cav_slot_style="normal").n_cavs == 0
    assert Scenario(cav_slot_style="normal").n_cav_slots == 10


def test_same_mix_names_and_bad_styles():
    assert parse_policy("same-mix").is_baseline
    assert build_policy(parse_policy("same-mix")).style == "normal"
    assert build_policy(parse_policy("same-mix:cautious")).style == "cautious"
    with pytest.raises(PolicyError, match="same-mix:<style> with style one of"):
        parse_policy("same-mix:sleepy")
    with pytest.raises(PolicyError, match="same-mix:<style>"):
        SameMixPolicy("same-mix:")
    with pytest.raises(ConfigError, match="'cav_slot_style' must be one of .*, got 'sleepy'"):
        Scenario(cav_slot_style="sleepy")
    with pytest.raises(PolicyError, match="not to the same-mix baseline"):
        parse_policy("same-mix", variant="diacc")


@pytest.mark.parametrize("backend", ["highway", "sumo"])
def test_same_mix_runs_with_the_cells_vehicles(backend):
    policy = SameMixPolicy("same-mix")
    cfg = policy.env_config(CELL, EvalSettings(backend, episode_steps=12))
    assert not cfg.use_psar and cfg.scenario.n_cavs == 0
    driver = EpisodeDriver(policy, cfg)
    try:
        row = run_episode(driver, CELL, 0, "test").row
        state = driver.state
    finally:
        driver.close()
    assert row["policy"] == "same-mix" and row["n_cavs"] == 0 and row["n_vehicles_seen"] == 20
    cav_slots = draw_population(CELL.scenario(), driver.road, CELL.seed(0, "test")).is_cav
    assert np.all(state.style[0, cav_slots] == NORMAL) and not state.is_cav.any()  # E = 1


def _obs(x_m: list[float], lane: list[int], road, alive=None) -> ActorObs:
    """ActorObs whose self_state carries x and lane as the builder normalises them."""
    c = len(x_m)
    self_state = np.zeros((c, 6), np.float32)
    self_state[:, 0] = np.asarray(x_m) / road.length_m
    self_state[:, 4] = np.asarray(lane) / (road.max_lanes - 1)
    fields = {f: np.zeros((c, 1)) for f in ActorObs.__dataclass_fields__}
    fields.update(self_state=self_state, alive=np.ones(c, bool) if alive is None else alive)
    return ActorObs(**fields)


def test_heuristic_leaves_an_ending_lane_toward_the_surviving_side():
    road = load_map("train-50")  # lanes 2 and 3 (left) end at 500 m
    lead = 500.0 - HEURISTIC_LEAVE_M
    x = [lead - 10, lead + 10, lead + 10, lead + 10, 100.0, 600.0]
    lane = [3, 3, 2, 1, 0, 1]
    actions = heuristic_actions(_obs(x, lane, road), road)
    # Far from the end: accelerate. Near it, lanes 3 and 2 move right (lane 3 over
    # lane 2, which ends at the same point); lanes 1 and 0 survive: accelerate.
    assert actions.tolist() == [ACCELERATE, LANE_RIGHT, LANE_RIGHT] + [ACCELERATE] * 3
    dead = heuristic_actions(_obs(x, lane, road, alive=np.zeros(6, bool)), road)
    assert np.all(dead == ACCELERATE)


def test_heuristic_on_a_right_drop_map_goes_left():
    import dataclasses

    road = dataclasses.replace(load_map("train-50"), drop_side="right")  # lanes 0, 1 end
    actions = heuristic_actions(_obs([420.0, 420.0, 420.0], [1, 0, 2], road), road)
    assert actions.tolist() == [LANE_LEFT, LANE_LEFT, ACCELERATE]


def test_heuristic_needs_the_road_and_runs_under_psar():
    policy = build_policy(parse_policy("heuristic"))
    assert policy.env_config(CELL, EvalSettings()).use_psar
    with pytest.raises(PolicyError, match="needs the road"):
        policy.act(_obs([0.0], [0], load_map("train-50")), first_step=True)


def test_eval_psar_horizon_reaches_every_policy_with_psar_and_is_recorded():
    """``diacc eval --psar-horizon``: rules and learners compared under the same PSAR."""
    cell = Cell("train-50", 25, 0.4, "D1")
    settings = EvalSettings(psar_horizon="headway")
    for name in ("heuristic", "cooperative", "accelerate"):
        assert build_policy(PolicySpec(name)).env_config(cell, settings).psar.horizon == "headway"
    default = build_policy(PolicySpec("heuristic")).env_config(cell, EvalSettings())
    assert default.psar.horizon == "headway"  # the default since 2026-12-02
    assert settings.describe()["settings"]["psar_horizon"] == "headway"
    # Unset, the key is absent, so results written before the option stay reusable.
    assert "psar_horizon" not in EvalSettings().describe()["settings"]
    with pytest.raises(ConfigError, match="'psar_horizon' must be one of .*, got 'soon'"):
        EvalSettings(psar_horizon="soon")


def test_an_episode_without_cavs_warns_nothing():
    """Pure HDV has no CAV: the logged CAV means are 0, not 0 / 0 with a RuntimeWarning
    printed by every `diacc simulate` / `eval` (issue 42)."""
    import warnings

    policy = PureHdvPolicy()
    driver = EpisodeDriver(policy, policy.env_config(CELL, EvalSettings(episode_steps=3)))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)
            driver.reset(CELL.seed(0, "test"))
            driver.env.step_arrays(np.zeros(0, np.int64))  # no CAV, no action
            logged = driver.env.transition.reward_terms  # of the batch of one the env stepped
            run_episode(driver, CELL, 0, "test")
    finally:
        driver.close()
    assert logged["individual"].tolist() == [0.0]
