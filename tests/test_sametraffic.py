"""``diacc table`` and ``plot flow`` pair and pool only episodes of the same traffic (issue 61).

Each case copies one real evaluation and changes one thing of its traffic (or
duplicates a row); the table and the figure refuse it with one line naming it.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from test_hostile4 import _damaged_copy, _one_line, _set

from diacc.cli import main
from diacc.experiments.evaluate import EPISODES_FILE, read_csv


def _eval(out: Path, grid: str, steps: int = 3) -> Path:
    argv = ["eval", "--policy", "pure-hdv", "--grid", grid, "--episodes", "2", "--no-progress"]
    assert main([*argv, "--episode-steps", str(steps), "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def results(tmp_path_factory) -> Path:
    """pure-hdv, 2 episodes of 3 steps of the train cell."""
    return _eval(tmp_path_factory.mktemp("same") / "pure-hdv", "train")


def _settings(**changes):
    """A change of ``meta.json``: its settings updated."""

    def change(meta: dict) -> dict:
        return {**meta, "settings": {**meta["settings"], **changes}}

    return change


def _everywhere(column: str, text: str):
    """A change of :func:`test_hostile4._rewrite`: ``column`` of every row becomes ``text``."""
    return lambda rows: (list(rows[0]), [{**r, column: text} for r in rows])


def _duplicated(rows):
    return list(rows[0]), [*rows, rows[0]]


LATE = _settings(highway_merges="late")  # a merge model absent from meta.json matches any


@pytest.mark.parametrize(
    "base_meta, meta, rows, message",
    [
        (None, _settings(episode_steps=4), None, "differ in episode length (4 vs 3)"),
        (None, None, _everywhere("style_preset", "paper"), "differ in style_preset (paper vs"),
        (LATE, _settings(highway_merges="early"), None, "highway merge model (early vs late)"),
        (None, None, _everywhere("stream", "validation"), "differ in stream (validation vs"),
        (None, None, _set("seed", "7"), "differ in seed of episode 0 (7 vs"),
        (None, None, _duplicated, "holds episode 0 of train-25_N25_rho0.40_D1 twice"),
    ],
)
def test_a_table_of_different_traffic_is_one_line(
    results, tmp_path, capsys, base_meta, meta, rows, message
):
    base = _damaged_copy(results, tmp_path / "base", base_meta)
    other = _damaged_copy(results, tmp_path / "other", meta, rows)
    _one_line(capsys, ["table", str(base), str(other)], message)


def test_a_table_of_the_same_traffic_pairs(results, tmp_path, capsys):
    same = _damaged_copy(results, tmp_path / "same")
    assert main(["table", str(results), str(same)]) == 0
    assert "pure-hdv" in capsys.readouterr().out


@pytest.mark.parametrize(
    "rows, message",
    [(_everywhere("map", "test-50"), "differ in map"), (_duplicated, "twice")],
)
def test_plot_flow_pools_one_traffic_per_point(tmp_path, capsys, rows, message):
    """Two files of series pure-hdv at 1200 veh/h: on two maps, or one holding a row twice."""
    grid = tmp_path / "grid.toml"
    grid.write_text(
        '[[cells]]\nmap = "train-50"\ncav_penetration = 0.4\nstyle_mix = "D1"\n'
        "inflow_vph = 1200\ndemand_s = 20\n"
    )
    first = _eval(tmp_path / "flow" / "a" / "pure-hdv" / "q1200", str(grid))
    second = tmp_path / "flow" / "b" / "pure-hdv" / "q1200"
    _damaged_copy(first, second, change=rows)
    assert {r["map"] for r in read_csv(second / EPISODES_FILE)} <= {"train-50", "test-50"}
    argv = ["plot", "flow", str(tmp_path / "flow"), "--out", str(tmp_path / "figure")]
    _one_line(capsys, argv, message)
