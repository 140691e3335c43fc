"""Explicit settings are never silently overwritten (issue 43, "One config system").

A value the user gave that another setting contradicts is a one-line error
before anything is written; a value left unset is derived as before (the
shipped configs, grids and checkpoints resolve to the same configs).
"""

from __future__ import annotations

import dataclasses
import os

import pytest

from diacc.cli import main
from diacc.config import (
    ConfigError,
    EnvConfig,
    TrainConfig,
    build_train_config,
    override,
    validate,
)
from diacc.experiments.grid import Cell
from diacc.sim.scenario import Demand, Release, Scenario, ScenarioError


def _train_fails(tmp_path, monkeypatch, capsys, *argv: str) -> str:
    """Run ``diacc train`` in an empty ``tmp_path``: exit 2, one line, nothing on disk."""
    monkeypatch.chdir(tmp_path)
    assert main(["train", "--no-progress", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("diacc: error: ") and "\n" not in err
    assert os.listdir(tmp_path) == []
    return err


def test_demand_refuses_a_vehicle_count_it_would_overwrite(tmp_path, monkeypatch, capsys):
    err = _train_fails(
        tmp_path,
        monkeypatch,
        capsys,
        *("--set", "env.scenario.kind=demand", "--set", "env.scenario.n_vehicles=40"),
    )
    assert "n_vehicles 40 contradicts the demand: inflow_vph 2400 x demand_s 300 s makes 200" in err
    with pytest.raises(ScenarioError, match="n_vehicles 40 contradicts the demand"):
        Scenario(kind="demand", n_vehicles=40)
    # the count it makes may be given (a stored config holds it), or left out
    assert Scenario(kind="demand", n_vehicles=200).n_vehicles == 200
    assert Scenario(kind="demand").n_vehicles == 200
    assert Scenario().n_vehicles == 25


@pytest.mark.parametrize(
    ("setting", "name"),
    [
        ("env.scenario.cav_slots=8", "cav_slots 8"),
        ("env.scenario.inflow_vph=3600", "inflow_vph 3600.0"),
        ("env.scenario.demand_s=600", "demand_s 600.0"),
    ],
)
def test_release_refuses_demand_settings_it_would_ignore(
    tmp_path, monkeypatch, capsys, setting, name
):
    err = _train_fails(tmp_path, monkeypatch, capsys, "--set", setting)
    assert f"env.scenario: {name} is a demand setting; a release (kind 'release') ignores it" in err
    key, value = setting.removeprefix("env.scenario.").split("=")
    with pytest.raises(ScenarioError, match="is a demand setting"):
        Scenario(**{key: float(value) if key != "cav_slots" else int(value)})
    # their defaults are fine (a stored release config's old 16 slots: test_config_schema)
    assert Scenario(inflow_vph=2400.0, demand_s=300.0, cav_slots="every").kind == "release"


def test_derived_count_follows_later_changes():
    """override rebuilds a scenario deriving its count again: a new inflow is not refused
    as contradicting the count the old one made, and a kind change resets the other
    kind's settings."""
    demand = build_train_config(sets=["env.scenario.kind=demand"])
    assert demand.env.scenario.n_vehicles == 200
    faster = override(demand, {"env.scenario.inflow_vph": 3600})
    assert faster.env.scenario.n_vehicles == 300
    release = override(faster, {"env.scenario.kind": "release"})
    assert isinstance(release.env.scenario, Release) and release.env.scenario.n_vehicles == 25
    assert not hasattr(release.env.scenario, "inflow_vph")  # a release has no demand settings
    assert Scenario(kind="demand").replace(demand_s=600).n_vehicles == 400
    # a grid's demand cell fixes its traffic, whatever the run's duration: its own
    # demand_s, else the default, and its count with it
    cell = Cell("train-50", 200, 0.4, "D1", 3600.0)
    assert cell.scenario(base=Scenario(kind="demand", demand_s=600)).n_vehicles == 300
    timed = Cell("train-50", 600, 0.4, "D1", 3600.0, demand_s=600.0)
    assert timed.scenario(base=Scenario(kind="demand", demand_s=120)).n_vehicles == 600


def test_variant_refuses_a_contradicting_psar_flag():
    with pytest.raises(ConfigError, match="env.use_psar=true contradicts variant 'mappo'"):
        TrainConfig(variant="mappo", env=EnvConfig(use_psar=True))
    with pytest.raises(ConfigError, match="env.use_psar=false contradicts variant 'diacc'"):
        TrainConfig(variant="diacc", env=EnvConfig(use_psar=False))
    # unset: the variant decides, as before
    assert TrainConfig(variant="mappo", env=EnvConfig(map="train-50")).env.use_psar is False
    assert TrainConfig(variant="diacc").env.use_psar is True
    assert TrainConfig(variant="mappo", env=EnvConfig(use_psar=False)).env.use_psar is False
    # a standalone env runs PSAR unless told otherwise
    assert EnvConfig().use_psar is None and EnvConfig().psar_enabled
    assert not EnvConfig(use_psar=False).psar_enabled
    assert override(EnvConfig(), {"use_psar": "false"}).use_psar is False


def test_batched_vector_needs_a_batched_backend(tmp_path, monkeypatch, capsys):
    err = _train_fails(
        tmp_path, monkeypatch, capsys, "--set", "vector=batched", "--backend", "sumo"
    )
    assert "vector 'batched' steps every env in one simulator, which backend 'sumo'" in err
    validate(build_train_config(backend="sumo", sets=["vector=process"]))
    validate(build_train_config(sets=["vector=batched"]))


def test_one_default_run_directory_rule():
    """``run_dir`` left unset is ``runs/<variant>-<backend>-<map>-s<seed>`` of the config
    itself, in Python as on the command line (issue 42 item 7: ``runs/diacc`` was the
    field's default while ``--help`` said the rule); a given one is kept."""
    assert TrainConfig().run_dir == "runs/diacc-highway-train-25-s1"
    assert TrainConfig(variant="mappo", seed=3).run_dir == "runs/mappo-highway-train-25-s3"
    assert build_train_config().run_dir == TrainConfig().run_dir
    # derived, it follows the fields it names; set, it stays
    moved = override(TrainConfig(), {"seed": 4, "env.backend": "sumo"})
    assert moved.run_dir == "runs/diacc-sumo-train-25-s4"
    assert override(TrainConfig(run_dir="out/r"), {"seed": 4}).run_dir == "out/r"
    assert override(TrainConfig(), {"seed": 4, "run_dir": "out/s"}).run_dir == "out/s"


def test_the_config_table_shows_a_derived_run_directory_as_unchanged():
    from diacc.console import config_table

    rows = {}
    table = config_table(TrainConfig(seed=5), "t")
    for key, value, default in zip(*(c._cells for c in table.columns), strict=True):
        rows[key.replace("[bold]", "").replace("[/bold]", "")] = (value, default)
    assert rows["run_dir"] == ("'runs/diacc-highway-train-25-s5'", "")
    assert rows["seed"] == ("5", "1")


def test_eval_settings_are_checked_like_every_config_section():
    """EvalSettings goes through the fields' checks: a backend, preset or step count out
    of range is a one-line ConfigError naming the field, before any episode runs."""
    from diacc.experiments.policies import EvalSettings

    for kwargs, match in [
        ({"backend": "carla"}, "'backend' must be one of highway, sumo, got 'carla'"),
        ({"style_preset": "calm"}, "'style_preset' must be one of .*, got 'calm'"),
        ({"episode_steps": 0}, r"'episode_steps' must be in \[1, 10000\], got 0"),
        ({"episode_steps": 2.5}, "'episode_steps' must be an integer, got 2.5"),
        ({"psar_full_brake": "never"}, "'psar_full_brake' must be one of"),
    ]:
        with pytest.raises(ConfigError, match=match) as err:
            EvalSettings(**kwargs)
        assert "\n" not in str(err.value)
    assert EvalSettings(episode_steps=40, style_preset="paper").episode_steps == 40


def test_scenario_ranges_go_through_the_field_checks():
    """Scenario's own ranges are field errors (one path for every section) and, typed
    through the config, name the dotted key."""
    with pytest.raises(ConfigError, match=r"config key 'cav_penetration' must be in \[0, 1\]"):
        Scenario(cav_penetration=1.5)
    with pytest.raises(ConfigError, match="config key 'env.scenario.cav_slots' must be 'every' or"):
        override(TrainConfig(), {"env.scenario.kind": "demand", "env.scenario.cav_slots": 0})
    with pytest.raises(ConfigError, match="'n_vehicles' must be an integer, got 2.5"):
        Scenario(n_vehicles=2.5)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--safety", "--episodes", "0"], "--episodes must be in [1, 10000], got 0"),
        (["--backend", "highway", "--timing-steps", "-3"], "--timing-steps must be in [1, 10000]"),
        (["--backend", "highway", "--steps", "1000000000"], "--steps must be in [1, 10000]"),
        (["--fidelity", "--inflow", "3600", "inf"], "--inflow must be a finite number, got inf"),
        (["--fidelity", "--demand-s", "0"], "--demand-s must be > 0, got 0.0"),
        (["--headroom", "--warmup-s", "-1"], "--warmup-s must be >= 0, got -1.0"),
        (["--headway", "--inflow", "3600"], "--inflow needs --headroom with --scenario demand"),
        (["--headroom", "--scenario", "demand", "--inflow", "1", "2"], "needs --inflow (one"),
    ],
)
def test_bench_options_are_checked_in_one_place(capsys, argv, message):
    """``diacc bench``'s shared options go through the fields' checks (BenchOptions):
    one line naming the flag, before any benchmark runs."""
    assert main(["bench", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("diacc: error: ") and "\n" not in err
    assert message in err


def test_scenario_is_release_or_demand_with_the_count_a_property():
    """Two types, ``Scenario = Release | Demand``: a demand's count is derived (a
    property, never a stored value that could disagree), a release has no demand
    settings; ``Scenario(kind=...)`` builds the one named."""
    release, demand = Scenario(), Scenario(kind="demand", inflow_vph=3600, demand_s=120)
    assert type(release) is Release and type(demand) is Demand
    assert isinstance(release, Scenario) and isinstance(demand, Scenario)
    assert not isinstance(TrainConfig(), Scenario)
    assert demand.n_vehicles == 120 and "n_vehicles" not in dataclasses.asdict(demand)
    assert dataclasses.asdict(release)["n_vehicles"] == 25
    assert not {"inflow_vph", "demand_s", "cav_slots"} & set(dataclasses.asdict(release))
    with pytest.raises(TypeError):
        Demand(n_vehicles=40)  # no such field: the count follows from the demand
    with pytest.raises(ValueError, match="init=False"):
        dataclasses.replace(release, kind="demand")  # the kind is the type
    # a kind change through the config rebuilds the section as the other type
    cfg = override(TrainConfig(), {"env.scenario.kind": "demand", "env.scenario.cav_slots": 8})
    assert type(cfg.env.scenario) is Demand and cfg.env.scenario.n_slots == 8
    assert type(override(TrainConfig(), {"env.scenario": demand}).env.scenario) is Demand
