"""benchmarks/studies/paper-convergence/speed_profile.py: the speed-distribution claim."""

import csv
import gzip
import subprocess
import sys
from pathlib import Path

from diacc.experiments.results_files import SPEED_COLUMNS, SPEEDS_FILE

SCRIPT = Path(__file__).parents[1] / "benchmarks/studies/paper-convergence/speed_profile.py"


def _speeds(path: Path, policy: str, episodes: list[list[float]], n_vehicles: int = 30) -> None:
    """A results directory whose only samples are ``episodes`` (speeds per episode) on
    the multilane segment of one test-50 cell."""
    path.mkdir(parents=True)
    with gzip.open(path / SPEEDS_FILE, "wt", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(SPEED_COLUMNS)
        for episode, speeds in enumerate(episodes):
            for step, speed in enumerate(speeds):
                cell = ["test-50", n_vehicles, 0.3, "D1"]
                row = [policy, "highway", *cell, episode, 0, step, 0.1 * step, speed]
                writer.writerow([*row, "multilane", True])


def test_levels_and_paired_changes_pool_the_seeds(tmp_path):
    backend = tmp_path / "eval/highway"
    _speeds(backend / "same-mix", "same-mix", [[2, 10, 10], [2, 2, 20], [10, 10, 10]])
    _speeds(backend / "diacc-train-50-s1", "diacc", [[4, 20, 20], [4, 4, 40], [20, 20, 20]])
    _speeds(backend / "diacc-train-50-s2", "diacc", [[4, 20, 20], [4, 4, 40], [20, 20, 20]])
    _speeds(backend / "pure-hdv", "pure-hdv", [[1, 1, 1]] * 3, n_vehicles=25)  # not a row here
    out = subprocess.run(
        [sys.executable, str(SCRIPT), str(tmp_path)], capture_output=True, text=True, check=True
    ).stdout
    assert "**test-50_N30_rho0.30_D1**" in out and "pure-hdv" not in out
    (mix,) = [line for line in out.splitlines() if line.startswith("| same-mix |")]
    # same-mix: 9 samples, median 10, IQR 2-10; 3 of 9 below 5 m/s; diacc's medians are twice
    # theirs in every episode (+100 %), and its 4 m/s samples are as many as their 2 m/s ones
    level = "| same-mix | multilane | 10.0 (2.0-10.0) | 33.3 % |"
    assert mix == f"{level} +100.0 % [+100.0, +100.0] | ≈ +0.0 pp [+0.0, +0.0] |"
    (ours,) = [line for line in out.splitlines() if line.startswith("| diacc |")]
    assert ours.startswith("| diacc | multilane | 20.0 (4.0-20.0) | 33.3 % |")


def test_results_without_speed_samples_are_one_line(tmp_path):
    (tmp_path / "eval/highway/same-mix").mkdir(parents=True)
    argv = [sys.executable, str(SCRIPT), str(tmp_path)]
    out = subprocess.run(argv, capture_output=True, text=True)
    assert out.returncode == 1 and "has no speeds.csv.gz" in out.stderr
    assert out.stderr.startswith("speed_profile.py: error: ") and "Traceback" not in out.stderr
