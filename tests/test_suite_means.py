"""suite_means.py (issue 60): a suite's mean delay per candidate against each reference,
paired by (cell, episode); ``--against`` adds result folders as references (the shipped
suite agent in the fine-tuned agents' card), ``--candidates`` pools one arm's seeds."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks/studies/suite-training/suite_means.py"
FIELDS = ["map", "n_vehicles", "cav_penetration", "style_mix", "inflow_vph", "episode"]


def _write(folder: Path, delays_s: dict[str, list[float]]) -> None:
    """One column of a card: per map the episodes' delays per vehicle."""
    folder.mkdir(parents=True)
    with (folder / "episodes.csv").open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow([*FIELDS, "delay_per_vehicle_s"])
        for name, delays in delays_s.items():
            for episode, delay in enumerate(delays):
                writer.writerow([name, 25, 0.4, "D1", 0, episode, delay])


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(SCRIPT), *args], capture_output=True, text=True, check=False
    )


def test_pairs_by_cell_and_episode_and_pools_the_chosen_candidates(tmp_path):
    where = tmp_path / "card" / "sumo" / "generated"
    _write(where / "heuristic", {"gen-a": [10.0, 20.0], "gen-b": [30.0, 40.0]})
    _write(where / "suite-s3", {"gen-a": [10.0, 10.0], "gen-b": [10.0, 10.0]})
    _write(where / "policy-1", {"gen-a": [5.0, 10.0], "gen-b": [15.0, 20.0]})  # half
    _write(where / "policy-2", {"gen-a": [20.0, 40.0], "gen-b": [60.0, 80.0]})  # twice
    _write(where / "policy-3", {"gen-a": [99.0, 99.0]})  # not chosen, not pooled
    out = _run(
        str(tmp_path / "card"), "generated", "sumo", "--against", "suite-s3",
        "--candidates", "policy-1", "policy-2",
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    assert any(
        line.startswith("generated policy-1 vs heuristic: 12.50 vs 25.00 s, -50.0 %")
        and line.endswith("4 pairs")
        for line in lines
    ), lines
    assert any(
        line.startswith("generated policy-2 vs suite-s3: 50.00 vs 10.00 s, +400.0 %")
        for line in lines
    )
    pooled = [line for line in lines if line.startswith("generated pooled (2 seeds) vs heuristic")]
    assert (
        pooled
        and pooled[0].startswith(
            "generated pooled (2 seeds) vs heuristic: 31.25 vs 25.00 s, +25.0 %"
        )
        and pooled[0].endswith("8 pairs")
    )
    assert not any("policy-3" in line for line in lines)


def test_a_missing_suite_is_a_one_line_error(tmp_path):
    out = _run(str(tmp_path), "generated", "sumo")
    assert out.returncode == 2
    assert "no results of suite 'generated' on sumo" in out.stderr
    assert "Traceback" not in out.stderr
