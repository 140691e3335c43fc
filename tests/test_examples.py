"""The training examples of ``examples/`` run end to end at tiny budgets.

Each runs as its own process, as a user would run it. A library that is not
installed skips its example with the extra to install (CI installs
``.[examples]``; RLlib is the ``rllib`` extra, outside CI, see examples/README.md).
"""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"

#: example -> (modules it needs, extra that installs them, arguments, a line it must print)
CASES = {
    "torchrl_mappo.py": (
        ("torchrl", "tensordict"),
        "torchrl",
        ["--iterations", "2", "--frames", "40"],
        "iteration 2: 40 env steps",
    ),
    "sb3_supersuit_ppo.py": (
        ("stable_baselines3", "supersuit"),
        "sb3",
        ["--steps", "64"],
        "trained 64 agent steps on 2 CAVs",
    ),
    "rllib_ppo.py": (("ray.rllib",), "rllib", ["--iterations", "1"], "iteration 1:"),
}

#: Controllers for ``diacc eval --policy examples.<module>:make``, tested elsewhere.
CONTROLLERS = {"keep_right_controller.py": "tests/test_userpolicy.py"}


def _missing(modules: tuple[str, ...]) -> str | None:
    """The first module that does not import (``ray.rllib`` is on disk with ``ray`` but
    fails to import without its extra's dependencies, so finding it is not enough)."""
    for name in modules:
        try:
            importlib.import_module(name)
        except ImportError:
            return name
    return None


def test_every_example_is_tested_and_listed():
    on_disk = sorted(p.name for p in EXAMPLES.glob("*.py"))
    assert on_disk == sorted([*CASES, *CONTROLLERS])
    readme = (EXAMPLES / "README.md").read_text()
    for name in on_disk:
        assert name in readme, f"{name} missing from examples/README.md"


@pytest.mark.parametrize("name", list(CASES))
def test_example_runs(name: str, tmp_path: Path) -> None:
    modules, extra, args, expected = CASES[name]
    missing = _missing(modules)
    if missing:
        pytest.skip(f"{missing} does not import (pip install -e '.[{extra}]')")
    env = {**os.environ, "PYTHONPATH": str(EXAMPLES.parent), "MPLBACKEND": "Agg"}
    proc = subprocess.run(
        [sys.executable, str(EXAMPLES / name), *args],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, f"{name} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    assert expected in proc.stdout


def test_rllib_constraints_fit_diacc_and_its_extra():
    # examples/rllib_check.sh installs diacc[rllib] under these pins: each must satisfy what
    # pyproject.toml asks of the package (gymnasium, torch) and of the rllib extra (ray).
    from packaging.requirements import Requirement

    from diacc.tomlfile import read_toml

    project = read_toml(EXAMPLES.parent / "pyproject.toml", ValueError)["project"]
    wanted = [*project["dependencies"], *project["optional-dependencies"]["rllib"]]
    ranges = {Requirement(r).name: Requirement(r).specifier for r in wanted}
    lines = (EXAMPLES / "rllib-constraints.txt").read_text().splitlines()
    pins = [Requirement(line) for line in lines if line and not line.startswith("#")]
    assert {p.name for p in pins} == {"ray", "gymnasium", "torch"}
    for pin in pins:
        (version,) = (s.version for s in pin.specifier)  # one exact pin each
        assert version in ranges[pin.name], f"{pin} is outside pyproject's {ranges[pin.name]}"
    readme = (EXAMPLES / "README.md").read_text()
    assert "rllib_check.sh" in readme and "rllib-constraints.txt" in readme
