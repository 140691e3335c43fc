"""README's main results table is regenerated from the committed result files (issue 42)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks" / "studies" / "test-stream"))

import check_readme_results  # noqa: E402


def test_readme_main_table_matches_the_committed_results(capsys):
    assert check_readme_results.main([]) == 0, capsys.readouterr().out


def test_a_changed_number_is_found(tmp_path, capsys):
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    row = next(line for line in text.splitlines() if line.startswith("| **DIACC greedy** |"))
    changed = tmp_path / "README.md"
    changed.write_text(text.replace(row, row.replace("-20.7 %", "-24.6 %")), encoding="utf-8")
    assert check_readme_results.main(["--readme", str(changed)]) == 1
    assert "DIFFERS" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("old", "new", "says"),
    [
        ("| -18.4 % [-21.9, -14.5] |", "| -19.4 % [-21.9, -14.5] |", "DIFFERS"),  # scorecard
        ("+13.8 % [+7.5, +21.1]", "+15.8 % [+7.5, +21.1]", "MISSING"),  # the paper paragraph
        ("-57.8 % [-63.9, -50.8]", "-58.7 % [-63.9, -50.8]", "MISSING"),  # demand
    ],
)
def test_a_changed_number_outside_the_main_table_is_found(tmp_path, capsys, old, new, says):
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert text.count(old) == 1
    changed = tmp_path / "README.md"
    changed.write_text(text.replace(old, new), encoding="utf-8")
    assert check_readme_results.main(["--readme", str(changed)]) == 1
    assert says in capsys.readouterr().out
