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


CRASH_PROBE = SCRIPT.with_name("crash_probe.py")


def test_crash_probe_names_each_colliding_pair_with_its_speeds_before():
    """Always accelerating without PSAR rear-ends a slower vehicle: the line gives both
    vehicles' lane, position and speed over the steps before the crash (the crash itself
    may zero the speeds); ``--stream test --only`` replays a chosen episode of another
    stream, named with its seed."""
    command = [sys.executable, str(CRASH_PROBE), "accelerate-nopsar", "1"]
    lines = subprocess.run(command, capture_output=True, text=True, check=True).stdout.splitlines()
    assert lines and all(line.startswith("episode 0 (seed ") for line in lines)
    assert all(line.count("before, lane/x m/speed m/s: ") == 2 for line in lines)
    assert "/25.0)" in lines[0]  # the CAV at its top speed the step before
    chosen = [*command, "--stream", "test", "--only", "2"]
    replayed = subprocess.run(chosen, capture_output=True, text=True, check=True).stdout
    assert replayed.startswith("episode 2 (seed ")
    bad = subprocess.run([*command[:2], "/no/such/run"], capture_output=True, text=True)
    assert bad.returncode == 1 and bad.stderr.startswith("crash_probe.py: error: unknown policy")
