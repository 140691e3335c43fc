"""benchmarks/studies/paper-convergence/action_probe.py counts what a policy picks."""

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).parents[1] / "benchmarks/studies/paper-convergence/action_probe.py"


def _probe():
    spec = importlib.util.spec_from_file_location("action_probe", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_shares_are_the_actions_the_policy_picked():
    probe = _probe()
    assert probe.action_shares("accelerate") == pytest.approx([0, 0, 0, 1, 0])
    shares = probe.action_shares("random")  # uniform draws: every action, none dominant
    assert shares.sum() == pytest.approx(1.0)
    assert np.all((shares > 0.1) & (shares < 0.3)), shares


def test_an_unknown_run_is_one_line():
    command = [sys.executable, str(SCRIPT), "/no/such/run"]
    out = subprocess.run(command, capture_output=True, text=True)
    assert out.returncode == 1 and out.stderr.startswith("action_probe.py: error: unknown policy")
    assert "Traceback" not in out.stderr
