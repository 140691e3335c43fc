"""``diacc plot flow``: outflow against inflow from real demand evaluations."""

from __future__ import annotations

import csv
import subprocess
import sys

import numpy as np
import pytest

from diacc.experiments.evaluate import evaluate
from diacc.experiments.flowplot import capacity, load_flow, mean_interval, plot_flow
from diacc.experiments.grid import make_cell
from diacc.experiments.plots import PlotError
from diacc.experiments.policies import EvalSettings, PolicySpec

INFLOWS = (1200.0, 3600.0)


@pytest.fixture(scope="module")
def flow_results(tmp_path_factory):
    """pure-hdv and same-mix, 2 episodes at each of two inflows (40 s of demand)."""
    root = tmp_path_factory.mktemp("flow")
    settings = EvalSettings("highway", episode_steps=40)
    for policy in ("pure-hdv", "same-mix"):
        for inflow in INFLOWS:
            cell = make_cell(
                {"map": "train-50", "cav_penetration": 0.4, "style_mix": "D1",
                 "inflow_vph": inflow, "demand_s": 40.0, "warmup_s": 10.0}
            )  # fmt: skip
            out = root / "highway" / policy / f"q{inflow:.0f}"
            evaluate(PolicySpec(policy), [cell], 2, out, settings, progress=False)
    return root


def test_points_are_the_episode_means_of_each_series_and_inflow(flow_results):
    points = load_flow([flow_results])
    assert {(p.series, p.inflow_vph) for p in points} == {
        (s, q) for s in ("pure-hdv", "same-mix") for q in INFLOWS
    }
    for p in points:
        path = flow_results / "highway" / p.series / f"q{p.inflow_vph:.0f}" / "episodes.csv"
        rows = list(csv.DictReader(path.open()))
        assert p.episodes == 2 and rows[0]["demand_s"] == "40.0"
        outflow = np.array([float(r["throughput_vph"]) for r in rows])
        assert p.outflow_vph == pytest.approx(outflow.mean())
        assert p.outflow_low <= p.outflow_vph <= p.outflow_high
    pure = [p for p in points if p.series == "pure-hdv"]
    top = max(p.outflow_vph for p in pure)
    cap, drop = capacity(points, "highway")
    assert cap == top and drop == pytest.approx((top - pure[-1].outflow_vph) / top)


def test_the_command_writes_the_figure(flow_results, tmp_path):
    out = tmp_path / "fig" / "flow"
    done = subprocess.run(
        [sys.executable, "-m", "diacc.cli", "plot", "flow", str(flow_results), "--out", str(out)],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert out.with_suffix(".png").stat().st_size > 10_000 and out.with_suffix(".pdf").exists()
    empty = tmp_path / "empty"
    empty.mkdir()
    done = subprocess.run(
        [sys.executable, "-m", "diacc.cli", "plot", "flow", str(empty), "--out", str(out)],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    assert done.returncode != 0 and done.stderr.strip().count("\n") == 0
    assert "no episodes.csv" in done.stderr


def test_interval_and_errors():
    assert mean_interval(np.array([5.0])) == (5.0, 5.0, 5.0)
    mean, low, high = mean_interval(np.array([1.0, 2.0, 3.0, 4.0]))
    assert mean == 2.5 and 1.0 <= low < mean < high <= 4.0
    with pytest.raises(PlotError, match="no episodes.csv"):
        plot_flow([], "x")


def test_a_table_tells_apart_results_of_one_policy_in_folders_of_one_name(flow_results, tmp_path):
    """``diacc table`` of ``a/q1200`` and ``b/q1200`` holding the same policy: two columns
    with their own numbers (they were one label, and one column's numbers twice)."""
    import shutil

    from diacc.experiments.report import build_table

    source = flow_results / "highway" / "same-mix" / "q1200"
    for name in ("a", "b"):
        shutil.copytree(source, tmp_path / name / "q1200")
    path = tmp_path / "b" / "q1200" / "episodes.csv"
    rows = list(csv.DictReader(path.open()))
    for row in rows:
        row["throughput_vph"] = str(float(row["throughput_vph"]) + 100.0)
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    table = build_table([tmp_path / "a" / "q1200", tmp_path / "b" / "q1200"], rows=("throughput",))
    assert table.columns == ["same-mix (highway) [a/q1200]", "same-mix (highway) [b/q1200]"]
    (cell,) = table.cells
    a, b = (table.stats[(cell.key, "throughput", c)].mean for c in table.columns)
    assert b == pytest.approx(a + 100.0)


def test_a_damaged_results_file_is_one_line(flow_results, tmp_path):
    """Results are read through the validating loader: a field that is not a number names
    the file and the field, and nothing is drawn."""
    import shutil

    copy = tmp_path / "x" / "q1200"
    shutil.copytree(flow_results / "highway" / "same-mix" / "q1200", copy)
    path = copy / "episodes.csv"
    rows = list(csv.DictReader(path.open()))
    rows[0]["throughput_vph"] = "lots"
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    with pytest.raises(PlotError, match="'throughput_vph' is not a number"):
        load_flow([tmp_path / "x"])
