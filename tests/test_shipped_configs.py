"""Every shipped config file (configs/*.toml) applies to TrainConfig and validates."""

from __future__ import annotations

from pathlib import Path

import pytest

from diacc.config import ConfigError, TrainConfig, override, validate
from diacc.tomlfile import read_toml

CONFIGS = sorted((Path(__file__).resolve().parent.parent / "configs").glob("*.toml"))


def test_configs_exist():
    assert CONFIGS, "configs/ holds no .toml file"


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_config_applies_and_validates(path):
    cfg = validate(override(TrainConfig(), read_toml(path, ConfigError)))
    assert cfg != TrainConfig()
