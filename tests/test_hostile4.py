"""Hostile input, fourth pass (issue 61): cells without CAVs, results files, late checks.

One test (or group) per root cause; each failed before its fix. Items 1, 2 and 6
of the issue are tested where their features are (test_userpolicy, test_demand).
"""

from __future__ import annotations

from pathlib import Path

import pytest

from diacc.cli import main
from diacc.experiments.evaluate import EPISODES_FILE, read_csv

CHECKPOINT = "checkpoints/diacc-train50-paper-congestion-s1.pt"


# ------------------------------------------------------------- 5: no CAVs for a checkpoint
@pytest.mark.parametrize("slots", ["own", "every"])
def test_a_checkpoint_plays_cells_without_cavs(tmp_path, slots):
    """rho = 0 gives the networks no agent slot: nothing to ask them, no empty batch."""
    grid = tmp_path / "grid.toml"
    cells = ["n_vehicles = 8", "inflow_vph = 1800\ndemand_s = 20"]  # a release, a demand
    head = '[[cells]]\nmap = "train-50"\ncav_penetration = 0.0\nstyle_mix = "D1"\n'
    grid.write_text("".join(f"{head}{c}\n" for c in cells))
    argv = ["eval", "--policy", CHECKPOINT, "--grid", str(grid), "--episodes", "1"]
    argv += ["--episode-steps", "3", "--agent-slots", slots, "--no-progress"]
    assert main([*argv, "--out", str(tmp_path)]) == 0
    assert {r["n_cavs"] for r in read_csv(Path(tmp_path) / EPISODES_FILE)} == {"0"}
