"""``diacc eval --agent-slots``: a policy drives its own ``cav_slots`` CAVs at once in a
demand cell, or every CAV (``every``). Real highway backend, the heuristic as policy."""

from __future__ import annotations

import dataclasses

import pytest
from helpers import SHORT_MAP

from diacc.cli import main
from diacc.config import ConfigError
from diacc.experiments.bench.headroom import SlotCountingDriver, demand_scenario
from diacc.experiments.evaluate import load_episodes, run_episode
from diacc.experiments.grid import Cell
from diacc.experiments.policies import EvalSettings, PolicySpec, build_policy
from diacc.sim.scenario import Scenario


def _unslotted_cav_steps(road: str, agent_slots: str) -> tuple[int, int]:
    """(agent slots, CAV-steps without a slot) of one tiny 100 % CAV demand episode driven
    by the heuristic with a single slot of its own."""
    demand = demand_scenario(3600, demand_s=30, warmup_s=10)  # 30 vehicles over 30 s
    policy = build_policy(PolicySpec("heuristic"))
    sim = dataclasses.replace(policy.base.sim, episode_steps=30)
    policy.base = dataclasses.replace(
        policy.base, scenario=dataclasses.replace(demand, cav_slots=1), sim=sim
    )
    cell = Cell(road, demand.n_vehicles, 1.0, "D1", demand.inflow_vph, 30.0, 10.0)
    settings = EvalSettings("highway", 30, "zipper", agent_slots=agent_slots)
    driver = SlotCountingDriver(policy, policy.env_config(cell, settings))
    try:
        run_episode(driver, cell, 0, "test")
    finally:
        driver.close()
    return driver.cfg.scenario.cav_slots, driver.unslotted_cav_steps


def test_every_cav_gets_a_slot_only_when_asked(tmp_path):
    road = tmp_path / "short.toml"
    road.write_text(SHORT_MAP)
    own_slots, own_unslotted = _unslotted_cav_steps(str(road), "own")
    every_slots, every_unslotted = _unslotted_cav_steps(str(road), "every")
    assert own_slots == 1 and own_unslotted > 0
    assert every_slots == 30 and every_unslotted == 0


def test_a_slot_per_cav_counts_the_episodes_cavs():
    demand = Scenario(kind="demand", inflow_vph=3600.0, demand_s=480.0, cav_penetration=0.4)
    assert demand.with_a_slot_per_cav().cav_slots == demand.n_cavs == 192
    humans = Scenario(kind="demand", inflow_vph=3600.0, demand_s=480.0, cav_penetration=0.0)
    assert humans.with_a_slot_per_cav().cav_slots == 1  # at least one (a config bound)


def test_results_record_it_only_when_every(tmp_path):
    grid = tmp_path / "q.toml"
    grid.write_text(
        '[[cells]]\nmap = "train-50"\ninflow_vph = 3600\ndemand_s = 40\nwarmup_s = 10\n'
        'cav_penetration = 0.4\nstyle_mix = "D1"\n'
    )
    common = ["eval", "--policy", "heuristic", "--grid", str(grid), "--episodes", "1"]
    common += ["--episode-steps", "40", "--no-progress"]
    assert main([*common, "--agent-slots", "every", "--out", str(tmp_path / "every")]) == 0
    assert main([*common, "--out", str(tmp_path / "own")]) == 0
    meta_every, _ = load_episodes(tmp_path / "every")
    meta_own, _ = load_episodes(tmp_path / "own")
    assert meta_every["settings"]["agent_slots"] == "every"
    assert "agent_slots" not in meta_own["settings"]  # older results stay reusable


def test_an_unknown_value_is_a_one_line_error():
    with pytest.raises(ConfigError, match="agent_slots"):
        EvalSettings(agent_slots="all")
