"""diacc.config.build_train_config: one builder for the CLI, sweep and reproduce.

Layers: defaults < TOML file < named options < --set; a variant-derived field
(env.use_psar) asked for against the variant is a one-line ConfigError; every
field's range is checked when any config is built (EnvConfig too).
"""

from __future__ import annotations

import math

import pytest

from diacc.cli import main
from diacc.config import (
    ConfigError,
    EnvConfig,
    ModelConfig,
    ObservationConfig,
    Scenario,
    SimConfig,
    TrainConfig,
    build_train_config,
    override,
    validate,
)
from diacc.experiments.sweepaxes import sweep_settings


def _toml(tmp_path, text: str):
    path = tmp_path / "c.toml"
    path.write_text(text)
    return path


def test_layers_apply_in_order(tmp_path):
    path = _toml(tmp_path, "n_envs = 4\nlr = 0.002\nseed = 7\n[env.reward]\nw_ego = 0.7\n")
    cfg = build_train_config(path)
    assert (cfg.n_envs, cfg.lr, cfg.seed, cfg.env.reward.w_ego) == (4, 0.002, 7, 0.7)
    cfg = build_train_config(path, envs=8, sets=["lr=0.003"])  # options beat the file
    assert (cfg.n_envs, cfg.lr, cfg.seed) == (8, 0.003, 7)
    cfg = build_train_config(path, envs=8, sets={"n_envs": 2})  # --set beats options
    assert cfg.n_envs == 2
    cfg = build_train_config(style_preset="paper", sets=["env.sim.style_preset=zipper"])
    assert cfg.env.sim.style_preset == "zipper"
    assert build_train_config(style_preset="paper").env.sim.style_preset == "paper"


def test_defaults_and_run_dir():
    cfg = build_train_config()
    assert cfg == override(TrainConfig(), {"run_dir": "runs/diacc-highway-train-25-s1"})
    # the default directory names the resolved run, whichever layer set its parts
    cfg = build_train_config(seed=3, sets=["variant=mappo"])
    assert cfg.run_dir == "runs/mappo-highway-train-25-s3"
    assert build_train_config(run_dir="out/r").run_dir == "out/r"
    assert build_train_config(sets=["run_dir=out/s"]).run_dir == "out/s"


def test_default_learner_is_the_small_one_and_needs_four_sequences():
    """Hidden sizes 64 and 4 minibatches by default (the paper's 128 and 1 are
    configs/paper-learner.toml); a rollout of fewer sequences says how to fix it."""
    cfg = TrainConfig()
    assert (cfg.model.hidden_dim, cfg.model.gru_hidden, cfg.minibatches) == (64, 64, 4)
    tiny = {"n_envs": 1, "rollout_steps": 20, "total_steps": 20, "env.sim.episode_steps": 20}
    with pytest.raises(
        ConfigError,
        match=r"^minibatches 4 exceeds the rollout's 2 sequences "
        r"\(n_envs 1 x rollout_steps 20 / chunk_len 10\); set minibatches <= 2",
    ):
        validate(override(TrainConfig(), tiny))
    assert validate(override(TrainConfig(), {**tiny, "minibatches": 2})).minibatches == 2


def test_bad_input_is_one_line(tmp_path):
    with pytest.raises(ConfigError, match="--set expects KEY=VALUE, got 'lr'"):
        build_train_config(sets=["lr"])
    with pytest.raises(ConfigError, match="does not exist"):
        build_train_config(tmp_path / "missing.toml")
    with pytest.raises(ConfigError, match="unknown config key 'variant.x'"):
        build_train_config(_toml(tmp_path, "[variant]\nx = 1\n"))


@pytest.mark.parametrize(
    ("variant", "value", "wanted"),
    [("diacc", "false", "without"), ("mappo-iadm", "0", "without"), ("mappo", "true", "with")],
)
def test_use_psar_against_the_variant_is_refused(tmp_path, variant, value, wanted):
    with pytest.raises(ConfigError, match=f"contradicts variant '{variant}'.*one {wanted} PSAR"):
        build_train_config(variant=variant, sets=[f"env.use_psar={value}"])
    # from a file too, with the variant given as an option after it
    path = _toml(tmp_path, f"[env]\nuse_psar = {value in ('true', '1')!s}\n".lower())
    with pytest.raises(ConfigError, match="contradicts variant"):
        build_train_config(path, variant=variant)
    with pytest.raises(ConfigError, match="contradicts variant"):
        override(TrainConfig(variant=variant), {"env.use-psar": value})


def test_use_psar_that_agrees_is_kept():
    assert not build_train_config(variant="mappo", sets=["env.use_psar=false"]).env.use_psar
    assert build_train_config(variant="diacc", sets=["env.use_psar=true"]).env.use_psar
    # a variant change without an explicit env.use_psar still derives it
    assert not override(TrainConfig(), {"variant": "diacc-nopsar"}).env.use_psar
    assert override(TrainConfig(variant="mappo"), {"variant": "diacc"}).env.use_psar


def test_sweep_over_use_psar_is_refused():
    with pytest.raises(ConfigError, match="--sweep: env.use_psar=false contradicts variant"):
        sweep_settings(build_train_config(), ["env.use_psar=true,false"])


def test_train_cli_refuses_the_contradiction(tmp_path, capsys):
    run = tmp_path / "run"
    argv = ["train", "--out", str(run), "--set", "env.use_psar=false", "--no-progress"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("diacc: error: env.use_psar=false contradicts variant 'diacc'")
    assert "\n" not in err and not run.exists()


def test_ranges_are_checked_when_any_config_is_built():
    with pytest.raises(ConfigError, match="'vehicle_length_m' must be > 0, got 0.0"):
        SimConfig(vehicle_length_m=0.0)
    with pytest.raises(ConfigError, match=r"'history_steps' must be in \[1, 100\], got 0"):
        ObservationConfig(history_steps=0)
    with pytest.raises(ConfigError, match="'leaky_slope' must be >= 0"):
        ModelConfig(leaky_slope=-0.1)
    with pytest.raises(ConfigError, match="'insert_start_m' must be a finite number"):
        EnvConfig(scenario=Scenario(insert_start_m=math.nan))
    with pytest.raises(ConfigError, match="'lr' must be > 0, got 0"):
        TrainConfig(lr=0)  # not only in validate(): at construction
    with pytest.raises(ConfigError, match="'device' must be one of auto, cpu, cuda, got 'tpu'"):
        TrainConfig(device="tpu")
    # through override, the message names the dotted key as typed
    with pytest.raises(ConfigError, match="config key 'env.sim.idm_delta' must be > 0, got 0.0"):
        override(TrainConfig(), {"env.sim.idm_delta": "0"})
    with pytest.raises(ConfigError, match="'style_mix\\[1\\]' must be a finite"):
        Scenario(style_mix=(0.2, math.nan, 0.2))  # a section checks itself when built
    # bounds are inclusive where the field allows them
    assert TrainConfig(gamma=1.0, entropy_coef=0.0).gamma == 1.0
    assert SimConfig(speed_change_mps=0.0).speed_change_mps == 0.0


def test_extra_maps_from_set_and_file_and_their_checks(tmp_path):
    cfg = build_train_config(map="train-50", sets=["extra_maps=train-25, test-50"])
    assert cfg.extra_maps == ("train-25", "test-50")
    path = _toml(tmp_path, 'extra_maps = ["train-25"]\n')
    assert build_train_config(path).extra_maps == ("train-25",)
    with pytest.raises(ConfigError, match="extra_maps' expects a list of names"):
        override(TrainConfig(), {"extra_maps": 3})
    # A repeated map is another share of the envs, not an error.
    validate(build_train_config(map="train-50", sets=["extra_maps=train-50,train-25"]))
    with pytest.raises(
        ConfigError, match="3 training maps .* need at least as many envs, got n_envs 2"
    ):
        validate(build_train_config(envs=2, sets=["extra_maps=train-50,test-25"]))


def test_train_cli_names_an_unknown_extra_map(tmp_path, capsys):
    run = tmp_path / "run"
    argv = ["train", "--out", str(run), "--set", "extra_maps=nowhere", "--no-progress"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("diacc: error: unknown map 'nowhere'") and "\n" not in err
    assert not run.exists()
