"""README's main results table is regenerated from the committed result files (issue 42)."""

from __future__ import annotations

import shutil
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


def _moved(text: str, old: str) -> str:
    """``text`` with ``old`` cut out of its sentence and put in a paragraph of its own."""
    assert text.count(old) == 1, old
    return text.replace(old, "", 1) + f"\n\nMoved: {old}.\n"


@pytest.mark.parametrize(
    "old",
    [
        "+4.6 % [+0.9, +10.9]",  # the 25 % map against the heuristic
        "(the heuristic: 4 of 10 SUMO episodes)",  # a collision count of the demand bullets
        "≈ +2.4 % [-4.4, +13.3]",  # 1 M steps against the heuristic
    ],
)
def test_a_number_out_of_its_sentence_is_missing(tmp_path, capsys, old):
    """A number that is still on the page but no longer in its sentence fails the check."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    changed = tmp_path / "README.md"
    changed.write_text(_moved(text, old), encoding="utf-8")
    assert check_readme_results.main(["--readme", str(changed)]) == 1
    assert "MISSING" in capsys.readouterr().out


def test_a_sentence_without_its_stream_is_missing(tmp_path, capsys):
    """The 1 M-step sentence must name its stream and the heuristic."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    old = "3 seeds pooled, 10 `test` episodes"
    assert text.count(old) == 1
    changed = tmp_path / "README.md"
    changed.write_text(text.replace(old, "3 seeds pooled, 10 episodes"), encoding="utf-8")
    assert check_readme_results.main(["--readme", str(changed)]) == 1
    assert "MISSING" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("page", "old", "new", "says"),
    [
        # paper-vs-ours row 11: source D's collisions under PSAR
        ("paper-vs-ours.md", "1 of 20 SUMO episodes each", "0 of 20 SUMO episodes each", "MISSING"),
        # paper-vs-ours row 3: the 25 % map agent against pure HDV
        ("paper-vs-ours.md", "SUMO +7.0 % [+5.1, +9.1]", "SUMO +7.9 % [+5.1, +9.1]", "MISSING"),
        # demand-training: the heuristic's crashed SUMO episodes at 4800 veh/h, every CAV
        (
            "demand-training.md",
            "| 18.6 (≈ +0.6 [-1.5, +2.7]) | 4 of 10 |",
            "| 18.6 (≈ +0.6 [-1.5, +2.7]) | 0 of 10 |",
            "DIFFERS",
        ),
        # the scorecard page's summary
        (
            "scorecard.md",
            "| zero-shot | sumo | 10 | 10 / 0 / 0 |",
            "| zero-shot | sumo | 10 | 9 / 1 / 0 |",
            "DIFFERS",
        ),
    ],
)
def test_a_changed_number_on_a_results_page_is_found(tmp_path, capsys, page, old, new, says):
    docs = tmp_path / "results"
    shutil.copytree(ROOT / "docs" / "results", docs)
    text = (docs / page).read_text(encoding="utf-8")
    assert text.count(old) == 1, old
    (docs / page).write_text(text.replace(old, new), encoding="utf-8")
    assert check_readme_results.main(["--docs", str(docs)]) == 1
    assert says in capsys.readouterr().out
