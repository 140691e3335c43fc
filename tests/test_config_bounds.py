"""Upper bounds of the size-like settings (issue 46, "Sizes without bounds").

A typo such as ``n_vehicles=1000000000000`` or ``model.hidden_dim=1000000000``
is one ``diacc: error:`` line naming the field, its value, the bound and why,
raised before anything is allocated or written, from every route a config
takes: ``--set``, a TOML file, a grid, a checkpoint's stored config.
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from diacc.cli import main
from diacc.config import (
    MAX_ROLLOUT_BYTES,
    ConfigError,
    ObservationConfig,
    TrainConfig,
    override,
    rollout_bytes,
    validate,
)
from diacc.envs.observation import ObservationSpec
from diacc.experiments.grid import GridError, load_grid
from diacc.learn.checkpoint import config_from_checkpoint
from diacc.sim.scenario import MAX_VEHICLES, Scenario, ScenarioError

#: (--set, what the one line must say)
BOMBS = [
    (
        "env.scenario.n_vehicles=1000000000000",
        "'env.scenario.n_vehicles' must be in [1, 2000], got 1000000000000 (",
    ),
    ("model.hidden_dim=1000000000", "'model.hidden_dim' must be in [1, 1024], got 1000000000 ("),
    (
        "env.obs.max_vehicles=100000000",
        "'env.obs.max_vehicles' must be in [1, 2000], got 100000000",
    ),
    ("env.sim.substeps=1e9", "'env.sim.substeps' expects int, got '1e9'"),
    ("env.sim.substeps=1000000000", "'env.sim.substeps' must be in [1, 100], got 1000000000 ("),
    ("env.sim.episode_steps=100000000", "'env.sim.episode_steps' must be in [1, 10000]"),
    ("n_envs=10000", "'n_envs' must be in [1, 1024], got 10000 ("),
    ("rollout_steps=100000000", "'rollout_steps' must be in [1, 10000]"),
    ("model.gat_heads=100000", "'model.gat_heads' must be in [1, 64]"),
    ("env.obs.n_neighbours=100000", "'env.obs.n_neighbours' must be in [1, 64]"),
    ("epochs=1000000000", "'epochs' must be in [1, 100]"),
]


@pytest.mark.parametrize(("setting", "message"), BOMBS)
def test_train_refuses_a_size_bomb_in_one_line_and_writes_nothing(
    tmp_path, capsys, monkeypatch, setting, message
):
    monkeypatch.chdir(tmp_path)
    assert main(["train", "--no-progress", "--set", setting]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("diacc: error: ") and "\n" not in err
    assert message in err
    assert os.listdir(tmp_path) == []  # no run directory, no runs/


def test_demand_duration_is_bounded_by_the_vehicles_it_makes(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    sets = ["env.scenario.kind=demand", "env.scenario.demand_s=1e300"]
    assert main(["train", "--no-progress", *[a for s in sets for a in ("--set", s)]]) == 2
    err = capsys.readouterr().err.strip()
    assert "env.scenario: demand_s 1e+300 s at inflow_vph 2400 makes" in err
    assert "at most 2000 (demand_s <= 3000 s:" in err and "\n" not in err
    assert os.listdir(tmp_path) == []
    with pytest.raises(ScenarioError, match="at most 2000"):
        Scenario(kind="demand", demand_s=3000.01)
    with pytest.raises(ConfigError, match="'demand_s' must be a finite number"):
        Scenario(kind="demand", demand_s=float("inf"))
    assert Scenario(kind="demand", demand_s=3000).n_vehicles == MAX_VEHICLES


def test_scenario_bounds_hold_for_python_callers():
    with pytest.raises(ConfigError, match=r"'n_vehicles' must be in \[1, 2000\], got 2001"):
        Scenario(n_vehicles=MAX_VEHICLES + 1)
    with pytest.raises(
        ConfigError, match=r"'cav_slots' must be 'every' or an integer in \[1, 2000\]"
    ):
        Scenario(kind="demand", cav_slots=10**9)
    assert Scenario(n_vehicles=MAX_VEHICLES).n_vehicles == MAX_VEHICLES


def test_a_grid_with_a_huge_count_is_one_line(tmp_path):
    grid = tmp_path / "huge.toml"
    grid.write_text('[product]\nmap = ["train-50"]\nn_vehicles = [1000000000000]\n')
    with pytest.raises(GridError, match=r"'n_vehicles' must be in \[1, 2000\]") as err:
        load_grid(grid)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    ("section", "field", "value"),
    [
        ("model", "hidden_dim", 10**9),
        ("env.sim", "substeps", 10**9),
        ("env.obs", "max_vehicles", 10**8),
    ],
)
def test_a_checkpoint_config_with_a_huge_size_is_refused(section, field, value):
    """A stored config goes through the same checks (no allocation from its sizes)."""
    from dataclasses import asdict

    stored = asdict(TrainConfig())
    node = stored
    for name in section.split("."):
        node = node[name]
    node[field] = value
    with pytest.raises(ConfigError, match=f"'{section}.{field}' must be in"):
        config_from_checkpoint({"config": stored})


@pytest.mark.parametrize(
    "obs",
    [{}, {"n_neighbours": 64, "history_steps": 100}, {"max_vehicles": 2000}, {"n_neighbours": 1}],
)
def test_rollout_estimate_stays_above_the_real_layout(obs):
    """The estimate of :func:`rollout_bytes` must not fall below the real observation
    sizes (else the memory bound would let a rollout through that does not fit)."""
    cfg = override(TrainConfig(), {**{f"env.obs.{k}": v for k, v in obs.items()}})
    spec = ObservationSpec.from_config(cfg.env.obs)
    slots = cfg.env.scenario.n_slots

    def size(shapes):
        return sum(int(np.prod(shape)) * dtype.itemsize for shape, dtype in shapes.values())

    real = (
        cfg.rollout_steps
        * cfg.n_envs
        * (size(spec.actor_shapes(slots)) + size(spec.critic_shapes()))
    )
    assert rollout_bytes(cfg) >= real


def test_validate_refuses_a_rollout_that_does_not_fit():
    cfg = override(
        TrainConfig(), {"n_envs": 1000, "rollout_steps": 5000, "env.sim.episode_steps": 5000}
    )
    assert rollout_bytes(cfg) > MAX_ROLLOUT_BYTES
    with pytest.raises(
        ConfigError, match=r"rollout's observations would take about 255 GiB .*at most 8 GiB"
    ):
        validate(cfg)
    validate(TrainConfig())  # the defaults fit with room to spare
    assert rollout_bytes(TrainConfig()) < MAX_ROLLOUT_BYTES / 50


def test_bounds_leave_the_shipped_settings_alone():
    assert ObservationConfig(max_vehicles=MAX_VEHICLES).max_vehicles == MAX_VEHICLES
    validate(override(TrainConfig(), {"model.hidden_dim": 256, "model.gru_hidden": 256}))


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (
            ["eval", "--policy", "heuristic", "--grid", "train", "--workers", "10000"],
            "--workers must be in [1, 64], got 10000 (each is a process",
        ),
        (["reproduce", "--jobs", "10000", "--dry-run"], "--jobs must be in [1, 64], got 10000 ("),
        (
            ["eval", "--policy", "heuristic", "--grid", "train", "--episodes", "1000000000"],
            "--episodes must be in [1, 10000], got 1000000000 (per cell",
        ),
    ],
)
def test_worker_processes_and_episodes_are_bounded(tmp_path, capsys, monkeypatch, argv, message):
    monkeypatch.chdir(tmp_path)
    assert main([*argv, "--out", "out"]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err
    assert os.listdir(tmp_path) == []


WIDE_MAP = """name = "wide"
lane_width_m = 3.2
[[segments]]
kind = "multilane"
length_m = 500
lanes = 7
speed_limit_mps = 25.0
"""


def test_a_map_wider_than_the_observation_is_refused_before_anything_is_written(
    tmp_path, capsys, monkeypatch
):
    """A 7-lane map parses (maps allow 16) but the observation's lane table holds 6: once
    found by the first observation, after config.json and train.log were written."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "wide.toml").write_text(WIDE_MAP)
    (tmp_path / "g.toml").write_text('[product]\nmap = ["wide.toml"]\n')
    for argv in (
        ["train", "--no-progress", "--map", "wide.toml", "--steps", "2000", "--envs", "2"],
        ["eval", "--policy", "heuristic", "--grid", "g.toml", "--out", "out"],
    ):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert "map 'wide' has 7 lanes; the observation layout holds at most" in err
        assert "\n" not in err
        assert sorted(os.listdir(tmp_path)) == ["g.toml", "wide.toml"]
