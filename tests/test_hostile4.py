"""Hostile input, fourth pass (issue 61): cells without CAVs, results files, late checks.

One test (or group) per root cause; each failed before its fix. Items 1, 2 and 6
of the issue are tested where their features are (test_userpolicy, test_demand).
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import pytest

import diacc
from diacc.cli import main
from diacc.experiments.evaluate import EPISODES_FILE, read_csv
from diacc.experiments.policies import PolicyError

REPO_ROOT = Path(__file__).resolve().parent.parent

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


# ------------------------------------------------------------- 4: results files, fully checked
def _rewrite(path: Path, change) -> None:
    """Rewrite ``path``'s CSV rows through ``change(rows) -> (columns, rows)``."""
    rows = read_csv(path)
    columns, rows = change(rows)
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, columns, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)


def _set(column: str, text: str):
    """A change of :func:`_rewrite`: ``column`` of the first row becomes ``text``."""

    def change(rows):
        rows[0][column] = text
        return list(rows[0]), rows

    return change


def _without(column: str):
    return lambda rows: ([c for c in rows[0] if c != column], rows)


@pytest.fixture(scope="module")
def results(tmp_path_factory) -> Path:
    """pure-hdv, 2 episodes of 3 steps of one cell."""
    out = tmp_path_factory.mktemp("results") / "pure-hdv"
    argv = ["eval", "--policy", "pure-hdv", "--grid", "train", "--episodes", "2"]
    assert main([*argv, "--episode-steps", "3", "--no-progress", "--out", str(out)]) == 0
    return out


ROW_DAMAGE = [
    (_without("mean_speed_mps"), "has no 'mean_speed_mps' column"),
    (_set("seed", "nan"), "field 'seed' is not a whole number ('nan')"),
    (_set("n_vehicles", "eight"), "field 'n_vehicles' is not a number ('eight')"),
]
META_DAMAGE = [
    (lambda meta: {}, "meta.json names no 'policy'"),
    (lambda meta: {**meta, "policy": 3}, "'policy' is 3, not text"),
]


def _damaged_copy(results: Path, to: Path, meta=None, change=None) -> Path:
    """``results`` as committed (merged files only), its meta changed by ``meta(meta)`` and
    its rows by ``change`` (:func:`_rewrite`)."""
    shutil.copytree(results, to, ignore=shutil.ignore_patterns("cells", "speeds.csv.gz"))
    if meta is not None:
        path = to / "meta.json"
        path.write_text(json.dumps(meta(json.loads(path.read_text()))))
    if change is not None:
        _rewrite(to / EPISODES_FILE, change)
    return to


def _one_line(capsys, argv: list[str], message: str) -> None:
    """``argv`` fails with exit status 2 and one line on stderr that says ``message``."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err


@pytest.mark.parametrize(
    "meta, change, message",
    [(m, None, t) for m, t in META_DAMAGE] + [(None, c, t) for c, t in ROW_DAMAGE],
)
def test_a_damaged_results_directory_in_a_table_is_one_line(
    results, tmp_path, capsys, meta, change, message
):
    copy = _damaged_copy(results, tmp_path / "copy", meta, change)
    _one_line(capsys, ["table", str(results), str(copy)], message)


@pytest.mark.parametrize("change, message", ROW_DAMAGE)
def test_damaged_committed_results_under_a_new_eval_are_one_line(
    results, tmp_path, capsys, change, message
):
    """eval keeps committed rows as done cells: it reads them as a table does, first."""
    copy = _damaged_copy(results, tmp_path / "copy", change=change)
    argv = ["eval", "--policy", "pure-hdv", "--grid", "train", "--episodes", "3"]
    _one_line(capsys, [*argv, "--episode-steps", "3", "--no-progress", "--out", str(copy)], message)
    assert not (copy / "cells").exists()


def test_plot_flow_of_a_bottleneck_that_passed_nothing(tmp_path):
    """Pure-HDV outflow 0 (3 steps: nobody reaches the end): no capacity, no drop to divide."""
    grid = tmp_path / "grid.toml"
    grid.write_text(
        '[[cells]]\nmap = "train-50"\ncav_penetration = 0.4\nstyle_mix = "D1"\n'
        "inflow_vph = 1200\ndemand_s = 20\n"
    )
    out = tmp_path / "flow" / "pure-hdv" / "q1200"
    argv = ["eval", "--policy", "pure-hdv", "--grid", str(grid), "--episodes", "1"]
    assert main([*argv, "--episode-steps", "3", "--no-progress", "--out", str(out)]) == 0
    assert float(read_csv(out / EPISODES_FILE)[0]["throughput_vph"]) == 0.0
    figure = tmp_path / "figure"
    assert main(["plot", "flow", str(tmp_path / "flow"), "--out", str(figure)]) == 0
    assert figure.with_suffix(".png").exists()


# ------------------------------------------------------------- 7: checked before any work
SCORECARD = ["scorecard", "--policy", "same-mix", "--suites", "train", "--backends", "highway"]


def test_a_scorecard_agent_that_is_no_checkpoint_is_refused_first(tmp_path, capsys):
    agent = str(REPO_ROOT / "configs" / "small-learner.toml")
    argv = [*SCORECARD, "--episodes", "2", "--agent", agent, "--out", str(tmp_path / "card")]
    _one_line(capsys, argv, "small-learner.toml")
    assert not (tmp_path / "card").exists()  # no candidate results written


def test_a_scorecard_file_that_is_a_folder_is_refused_first(tmp_path, capsys):
    (tmp_path / "scorecard.json").mkdir()
    _one_line(capsys, [*SCORECARD, "--episodes", "2", "--out", str(tmp_path)], "is a folder")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scorecard.json"]


def test_train_into_a_tb_that_cannot_be_a_folder_is_refused_first(tmp_path, capsys):
    """TensorBoard found it in its writer thread (a read-only tb/ too, for other users
    than root); now it is one line before the first update, and nothing else is written."""
    (tmp_path / "tb").write_text("")
    argv = ["train", "--steps", "40", "--envs", "2", "--set", "rollout_steps=20"]
    argv += ["--set", "env.sim.episode_steps=20", "--no-progress", "--out", str(tmp_path)]
    _one_line(capsys, argv, "cannot write into")  # the config table goes to stdout
    assert not (tmp_path / "checkpoint.pt").exists() and not (tmp_path / "config.json").exists()


def test_a_map_segment_shorter_than_a_metre_is_refused(tmp_path, capsys):
    road = tmp_path / "road.toml"
    segment = '[[segments]]\nkind = "multilane"\nlanes = 3\nspeed_limit_mps = 25.0\n'
    road.write_text(
        f'name = "r"\nlane_width_m = 3.2\n{segment}length_m = 300\n{segment}length_m = 1e-300\n'
    )
    _one_line(capsys, ["simulate", "--map", str(road)], "length_m' must be a finite number >= 1")


def test_a_grid_demand_of_zero_seconds_is_refused(tmp_path, capsys):
    """0 stood for the default: the cell ran 300 s and was recorded as 0."""
    grid = tmp_path / "grid.toml"
    grid.write_text(
        '[[cells]]\nmap = "train-50"\ncav_penetration = 0.4\nstyle_mix = "D1"\n'
        "inflow_vph = 1200\ndemand_s = 0\n"
    )
    argv = ["eval", "--policy", "same-mix", "--grid", str(grid), "--episodes", "1"]
    _one_line(capsys, [*argv, "--out", str(tmp_path / "out")], "demand_s must be > 0 s, got 0")


@pytest.mark.parametrize("command", ["eval", "simulate"])
def test_highway_merges_on_sumo_are_refused(tmp_path, capsys, command):
    argv = ["eval", "--policy", "same-mix", "--grid", "train", "--episodes", "1"]
    argv = [*argv, "--out", str(tmp_path)] if command == "eval" else ["simulate"]
    argv += ["--backend", "sumo", "--highway-merges", "early"]
    _one_line(capsys, argv, "--highway-merges early applies to the highway backend, not sumo")


def test_load_policy_takes_sampled_as_a_bool():
    with pytest.raises(PolicyError, match="sampled must be True or False, got 'yes'"):
        diacc.load_policy(CHECKPOINT, sampled="yes")
