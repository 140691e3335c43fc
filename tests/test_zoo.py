"""PettingZoo entry points: ``diacc.parallel_env`` / ``diacc.env`` pass PettingZoo's API tests."""

from __future__ import annotations

import re

import numpy as np
import pytest
from pettingzoo import AECEnv, ParallelEnv
from pettingzoo.test import api_test, parallel_api_test

import diacc
from diacc.config import ConfigError

SMALL = {"scenario": {"n_vehicles": 8, "cav_penetration": 0.25}}


def test_exports_and_versioned_name():
    assert {"parallel_env", "env", "__version__"} <= set(diacc.__all__)
    env = diacc.parallel_env(**SMALL)
    try:
        assert isinstance(env, ParallelEnv)
        assert re.fullmatch(r"[a-z_]+_v\d+", env.metadata["name"])
        assert env.config.scenario.n_vehicles == 8 and env.num_agents == 0
        assert env.possible_agents == ["cav_0", "cav_1"]
    finally:
        env.close()


def test_parallel_env_passes_parallel_api_test():
    env = diacc.parallel_env(map="train-50", **SMALL)
    try:
        parallel_api_test(env, num_cycles=20)
    finally:
        env.close()


def test_aec_env_passes_api_test():
    env = diacc.env(**SMALL)
    try:
        assert isinstance(env, AECEnv)
        api_test(env, num_cycles=20)
    finally:
        env.close()


def test_same_seed_same_observations():
    first, second = diacc.parallel_env(**SMALL), diacc.parallel_env(**SMALL)
    try:
        a, _ = first.reset(seed=3)
        b, _ = second.reset(seed=3)
        for agent in a:
            for key in a[agent]:
                np.testing.assert_array_equal(a[agent][key], b[agent][key])
    finally:
        first.close()
        second.close()


def test_unknown_config_key_is_a_one_line_error():
    with pytest.raises(ConfigError, match="unknown config key 'lanes'"):
        diacc.parallel_env(lanes=3)


def test_env_factory_in_a_fresh_interpreter():
    """``diacc.env`` must be the factory before any submodule import too."""
    import subprocess
    import sys

    code = (
        "import diacc; e = diacc.env(scenario={'n_vehicles': 6}); e.reset(seed=0); "
        "print(type(e).__name__, len(e.agents))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["OrderEnforcingWrapper", "2"]
