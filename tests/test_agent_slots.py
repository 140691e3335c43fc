"""``diacc eval --agent-slots``: a policy drives every CAV of a demand cell (``every``, the
default), its own ``cav_slots`` at once (``own``) or a cap N. Real highway backend, the
heuristic as policy."""

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


def _unslotted_cav_steps(road: str, agent_slots: int | str) -> tuple[int, int]:
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
    return driver.cfg.scenario.n_slots, driver.unslotted_cav_steps


def test_every_cav_gets_a_slot_unless_a_cap_is_asked(tmp_path):
    road = tmp_path / "short.toml"
    road.write_text(SHORT_MAP)
    assert EvalSettings().agent_slots == "every"  # the default
    every_slots, every_unslotted = _unslotted_cav_steps(str(road), "every")
    assert every_slots == 30 and every_unslotted == 0
    own_slots, own_unslotted = _unslotted_cav_steps(str(road), "own")
    assert own_slots == 1 and own_unslotted > 0
    cap_slots, cap_unslotted = _unslotted_cav_steps(str(road), 2)
    assert cap_slots == 2 and 0 < cap_unslotted < own_unslotted


def test_a_slot_per_cav_counts_the_episodes_cavs():
    demand = Scenario(kind="demand", inflow_vph=3600.0, demand_s=480.0, cav_penetration=0.4)
    assert demand.cav_slots == "every" and demand.n_slots == demand.n_cavs == 192
    capped = demand.replace(cav_slots=16)
    assert capped.n_slots == 16 and capped.with_a_slot_per_cav().n_slots == 192
    humans = Scenario(kind="demand", inflow_vph=3600.0, demand_s=480.0, cav_penetration=0.0)
    assert humans.n_slots == 0


def test_results_record_them_unless_own(tmp_path):
    grid = tmp_path / "q.toml"
    grid.write_text(
        '[[cells]]\nmap = "train-50"\ninflow_vph = 3600\ndemand_s = 40\nwarmup_s = 10\n'
        'cav_penetration = 0.4\nstyle_mix = "D1"\n'
    )
    common = ["eval", "--policy", "heuristic", "--grid", str(grid), "--episodes", "1"]
    common += ["--episode-steps", "40", "--no-progress"]
    assert main([*common, "--out", str(tmp_path / "every")]) == 0  # the default
    assert main([*common, "--agent-slots", "own", "--out", str(tmp_path / "own")]) == 0
    meta_every, _ = load_episodes(tmp_path / "every")
    meta_own, _ = load_episodes(tmp_path / "own")
    assert meta_every["settings"]["agent_slots"] == "every"
    assert "agent_slots" not in meta_own["settings"]  # older results stay reusable
    assert EvalSettings(agent_slots=8).describe()["settings"]["agent_slots"] == 8


def test_a_release_records_no_agent_slots(tmp_path):
    """A release slots every CAV whatever the setting: its results of before the default
    became ``every`` stay reusable."""
    from diacc.experiments.evaluate import evaluation_meta

    policy = build_policy(PolicySpec("heuristic"))
    release = Cell("train-50", 8, 0.5, "D1")
    meta, _ = evaluation_meta(policy, [release], EvalSettings())
    assert "agent_slots" not in meta["settings"]


@pytest.mark.parametrize("value", ["all", 0, 2001, True])
def test_an_unknown_value_is_a_one_line_error(value):
    with pytest.raises(ConfigError, match="agent_slots.*must be one of every, own or an integer"):
        EvalSettings(agent_slots=value)


@pytest.mark.parametrize("command", ["eval", "train"])
def test_the_option_refuses_a_word_it_does_not_know(command, capsys):
    with pytest.raises(SystemExit) as exc:
        main([command, "--agent-slots", "all"])
    assert exc.value.code == 2
    assert "--agent-slots: must be every" in capsys.readouterr().err
