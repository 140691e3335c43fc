"""Every shipped config file (configs/*.toml) applies to TrainConfig and validates."""

from __future__ import annotations

from pathlib import Path

import pytest

from diacc.config import PAPER_LEARNER, ConfigError, TrainConfig, override, validate
from diacc.tomlfile import read_toml

CONFIGS = sorted((Path(__file__).resolve().parent.parent / "configs").glob("*.toml"))


def test_configs_exist():
    assert CONFIGS, "configs/ holds no .toml file"


#: Files kept although they equal the defaults (their comment says so): the small
#: learner became the default, and the commands of committed results name its file.
EQUAL_TO_DEFAULTS = {"small-learner.toml"}


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_config_applies_and_validates(path):
    cfg = validate(override(TrainConfig(), read_toml(path, ConfigError)))
    assert (cfg == TrainConfig()) == (path.name in EQUAL_TO_DEFAULTS)


def test_paper_learner_file_is_the_named_constant():
    """configs/paper-learner.toml and diacc.config.PAPER_LEARNER (used by the benchmarks)
    are the same learner: hidden 128, GRU 128, one minibatch."""
    path = CONFIGS[0].parent / "paper-learner.toml"
    from_file = override(TrainConfig(), read_toml(path, ConfigError))
    assert from_file == override(TrainConfig(), PAPER_LEARNER)
    assert (from_file.model.hidden_dim, from_file.model.gru_hidden) == (128, 128)
    assert from_file.minibatches == 1


def test_nopsar_recipe_is_the_shipped_nopsar_agents():
    """configs/nopsar.toml is the recipe the shipped no-PSAR agent was trained with: its
    stored config differs from the file's only in what the command line gave (steps,
    seed, threads, run directory), so the file's command reproduces that run."""
    import dataclasses

    import torch

    from diacc.learn.checkpoint import config_from_checkpoint

    root = CONFIGS[0].parent.parent
    recipe = validate(override(TrainConfig(), read_toml(root / "configs/nopsar.toml", ConfigError)))
    path = root / "checkpoints/diacc-nopsar-train50-both-realistic-brake4-ent03-s5.pt"
    shipped = config_from_checkpoint(torch.load(path, map_location="cpu", weights_only=True))
    differ = {
        f.name
        for f in dataclasses.fields(recipe)
        if getattr(recipe, f.name) != getattr(shipped, f.name)
    }
    assert differ == {"total_steps", "seed", "torch_threads", "run_dir"}
    assert not shipped.env.use_psar and recipe.variant == "diacc-nopsar"


def test_nopsar_recipe_on_sumo_alone_is_the_earlier_agents():
    """configs/nopsar.toml's comment trains the earlier SUMO-only recipe (the agent shipped
    before, seed 2 of docs/results/nopsar-learning.md's `ent03-sumo-brake4`) with
    ``--backend sumo --set mix.maps=``: that run's stored config, but for the command
    line's keys and the mix, which an empty map list turns off."""
    import dataclasses

    import torch

    from diacc.config.overrides import build_train_config
    from diacc.learn.checkpoint import config_from_checkpoint

    root = CONFIGS[0].parent.parent
    recipe = validate(
        build_train_config(root / "configs/nopsar.toml", backend="sumo", sets=["mix.maps="])
    )
    run = "benchmarks/studies/nopsar-learning/results/own-penalty50-ent03-sumo-brake4/runs"
    earlier = config_from_checkpoint(
        torch.load(
            root / run / "diacc-nopsar-s2/checkpoint.pt", map_location="cpu", weights_only=True
        )
    )
    differ = {
        f.name
        for f in dataclasses.fields(recipe)
        if getattr(recipe, f.name) != getattr(earlier, f.name)
    }
    assert differ <= {"total_steps", "seed", "torch_threads", "run_dir", "mix"}
    assert not recipe.mix.on and not earlier.mix.on and recipe.env == earlier.env
