"""`diacc table` on a tiny synthetic results set, against hand-computed numbers."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import pytest

from diacc.cli import main
from diacc.experiments.report import build_table, render_table

COLUMNS = [
    "policy",
    "backend",
    "sumo_version",
    "style_preset",
    "map",
    "n_vehicles",
    "cav_penetration",
    "style_mix",
    "episode",
    "mean_speed_mps",
    "std_speed_mps",
    "n_speed_samples",
    "p_we",
    "p_sce",
]


def _results(path: Path, policy: str, rows: list[tuple]) -> Path:
    """rows: (episode, mean, std, n_samples, p_we, p_sce) of cell train-25 N25 rho0.4 D1."""
    path.mkdir(parents=True)
    (path / "meta.json").write_text(json.dumps({"policy": policy, "backend": "sumo"}))
    with open(path / "episodes.csv", "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(COLUMNS)
        for ep, mean, std, n, we, sce in rows:
            writer.writerow(
                [
                    policy,
                    "sumo",
                    "SUMO 1.28.0",
                    "paper",
                    "train-25",
                    25,
                    0.4,
                    "D1",
                    ep,
                    mean,
                    std,
                    n,
                    we,
                    sce,
                ]
            )
    return path


@pytest.fixture()
def results(tmp_path):
    # pure HDV: episode speeds 10 +- 2 (100 samples) and 14 +- 0 (300 samples)
    #   pooled mean = (10*100 + 14*300)/400 = 13; E[v^2] = (100*(4+100) + 300*196)/400 = 173
    #   pooled std = sqrt(173 - 169) = 2. p(WE) = 20%, 40% -> 30 +- 10; p(SCE) 8%, 8% -> 8 +- 0
    hdv = _results(
        tmp_path / "hdv",
        "pure-hdv",
        [(0, 10.0, 2.0, 100, 0.2, 0.08), (1, 14.0, 0.0, 300, 0.4, 0.08)],
    )
    # DIACC: speeds 15 +- 1 and 17 +- 1 (200 each): mean 16, E[v^2] = (226 + 290)/2 = 258,
    #   std = sqrt(258 - 256) = sqrt(2); p(WE) 0%, 10% -> 5 +- 5; p(SCE) 0, 0
    #   change: speed (16-13)/13 = +23.1 %, p(WE) 5 - 30 = -25 pp, p(SCE) 0 - 8 = -8 pp
    diacc = _results(
        tmp_path / "diacc", "diacc", [(0, 15.0, 1.0, 200, 0.0, 0.0), (1, 17.0, 1.0, 200, 0.1, 0.0)]
    )
    return hdv, diacc


def test_table_numbers_are_exact(results):
    table = build_table(list(results))
    (cell,) = table.cells
    speed_hdv = table.stats[(cell.key, "speed", "pure-hdv")]
    speed_diacc = table.stats[(cell.key, "speed", "diacc")]
    assert (speed_hdv.mean, speed_hdv.std) == pytest.approx((13.0, 2.0))
    assert (speed_diacc.mean, speed_diacc.std) == pytest.approx((16.0, 2**0.5))
    we = table.stats[(cell.key, "p_we", "pure-hdv")]
    assert (we.mean, we.std, we.n_episodes) == pytest.approx((30.0, 10.0, 2))
    assert table.change(cell, "speed", "diacc") == pytest.approx(300 / 13)
    assert table.change(cell, "p_we", "diacc") == pytest.approx(-25.0)  # pp
    assert table.change(cell, "p_sce", "diacc") == pytest.approx(-8.0)
    assert table.change(cell, "speed", "pure-hdv") is None
    assert table.best(cell, "speed") == {"diacc"} and table.best(cell, "p_sce") == {"diacc"}

    markdown = render_table(table, "markdown")
    assert (
        "| N=25, rho=0.4, D1 | Speed (m/s) | 13.00 ± 2.00 | **16.00 ± 1.41** (+23.1 %) |"
        in markdown
    )
    assert "| p(WE) (%) | 30.00 ± 10.00 | **5.00 ± 5.00** (-25.0 pp) |" in markdown
    assert "| p(SCE) (%) | 8.00 ± 0.00 | **0.00 ± 0.00** (-8.0 pp) |" in markdown
    assert "SUMO 1.28.0, style preset paper, 2 episodes per cell" in markdown

    latex = render_table(table, "latex")
    assert r"\textbf{16.00 $\pm$ 1.41} (+23.1 \%)" in latex and r"\multirow{3}{*}" in latex

    rows = list(csv.DictReader(io.StringIO(render_table(table, "csv"))))
    speed = {r["policy"]: r for r in rows if r["metric"] == "speed"}
    assert float(speed["diacc"]["change"]) == pytest.approx(300 / 13)
    assert speed["diacc"]["best"] == "1" and speed["pure-hdv"]["change"] == ""


def test_speed_std_over_episodes(results):
    table = build_table(list(results), speed_std="episodes")
    stat = table.stats[(table.cells[0].key, "speed", "pure-hdv")]
    assert (stat.mean, stat.std) == pytest.approx((12.0, 2.0))  # episode means 10 and 14


def test_table_cli_formats(results, tmp_path, capsys):
    assert main(["table", *map(str, results)]) == 0
    assert "**16.00 ± 1.41** (+23.1 %)" in capsys.readouterr().out
    assert (
        main(["table", *map(str, results), "--format", "csv", "--out", str(tmp_path / "t.csv")])
        == 0
    )
    assert (tmp_path / "t.csv").read_text().startswith("map,n_vehicles")


def _results_with_safety(path: Path, policy: str, episodes: list[tuple]) -> Path:
    """episodes: (mean speed, p_we, collision 0/1, arrived fraction), 100 samples, std 1."""
    path.mkdir(parents=True)
    meta = {"policy": policy, "backend": "highway"}
    if policy != "pure-hdv":
        meta.update(checkpoint="/x/checkpoint.pt", update=10, trained_on="highway")
        meta.update(trained_steps=4000, total_steps=4000)
    (path / "meta.json").write_text(json.dumps(meta))
    columns = [*COLUMNS, "collision", "arrived_fraction"]
    with open(path / "episodes.csv", "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(columns)
        for ep, (speed, we, crash, arrived) in enumerate(episodes):
            writer.writerow(
                [policy, "highway", "", "realistic", "train-25", 25, 0.4, "D1", ep]
                + [speed, 1.0, 100, we, 0.0, crash, arrived]
            )
    return path


def test_slower_or_crashier_policies_are_not_ranked(tmp_path):
    hdv = _results_with_safety(tmp_path / "hdv", "pure-hdv", [(20.0, 0.2, 0, 1.0)])
    # 30 % slower, fewer waiting events: its lower p(WE) must not be bold
    slow = _results_with_safety(tmp_path / "slow", "mappo", [(14.0, 0.0, 0, 0.5)])
    # faster but crashes: not ranked either
    crashy = _results_with_safety(tmp_path / "crashy", "diacc-nopsar", [(23.0, 0.0, 1, 0.8)])
    table = build_table([hdv, slow, crashy], rows=("speed", "p_we", "collision", "arrived"))
    (cell,) = table.cells
    assert not table.ranked(cell, "mappo") and not table.ranked(cell, "diacc-nopsar")
    assert table.marks(cell, "p_we") == (set(), set())  # only pure HDV is ranked
    good = _results_with_safety(tmp_path / "good", "diacc", [(22.0, 0.04, 0, 1.0)])
    ok = _results_with_safety(tmp_path / "ok", "mappo-iadm", [(21.0, 0.08, 0, 1.0)])
    table = build_table([hdv, slow, ok, good], rows=("speed", "p_we", "collision", "arrived"))
    assert table.marks(cell, "speed") == ({"diacc"}, {"mappo-iadm"})
    assert table.marks(cell, "p_we") == ({"diacc"}, {"mappo-iadm"})
    assert table.marks(cell, "collision")[0] == {"pure-hdv", "mappo-iadm", "diacc"}

    markdown = render_table(table, "markdown")
    assert (
        "| Collision (%) | **0.00 ± 0.00** | 0.00 ± 0.00 (+0.0 pp) | **0.00 ± 0.00** (+0.0 pp) |"
        in markdown
    )
    assert "| Arrived (%) | **100.00 ± 0.00** | 50.00 ± 0.00 (-50.0 pp) |" in markdown
    assert "| 14.00 ± 1.00 (-30.0 %) | _21.00 ± 1.00_ (+5.0 %) | **22.00 ± 1.00** (+10.0 %) |" in (
        markdown
    )
    caption = markdown.splitlines()[0]
    assert caption == (
        "Table: train-25: 1 episode per cell, HDV style preset realistic, seed stream legacy; "
        "training budget "
        "(env steps): mappo 4,000, mappo-iadm 4,000, diacc 4,000"
    )
    assert "1 episodes" not in markdown and "ranked only columns no slower" in markdown

    latex = render_table(table, "latex")
    assert latex.startswith(r"% preamble: \usepackage{booktabs} \usepackage{multirow}")
    assert r"\caption{train-25: 1 episode per cell" in latex and r"\multirow{4}{*}" in latex
    assert r"\underline{21.00 $\pm$ 1.00}" in latex and r"\end{table}" in latex
    csv_rows = list(csv.DictReader(io.StringIO(render_table(table, "csv"))))
    marks = {r["policy"]: r["best"] for r in csv_rows if r["metric"] == "speed"}
    assert marks == {"pure-hdv": "0", "mappo": "0", "mappo-iadm": "2", "diacc": "1"}


def test_rows_the_results_lack_are_one_line_errors(results):
    with pytest.raises(ValueError, match="no results directory has the data of row 'collision'"):
        build_table(list(results), rows=("speed", "collision"))
    with pytest.raises(ValueError, match="unknown table row 'speedy'"):
        build_table(list(results), rows=("speedy",))


def test_table_cli_rows_option(results, capsys):
    assert main(["table", *map(str, results), "--rows", "speed,collision"]) == 2
    assert "has the data of row 'collision'" in capsys.readouterr().err
    assert main(["table", *map(str, results), "--rows", "p_we"]) == 0
    out = capsys.readouterr().out
    assert "p(WE) (%)" in out and "Speed (m/s)" not in out


def test_columns_are_ranked_and_compared_within_their_backend(results, tmp_path):
    hdv, diacc = results  # both on sumo
    fast = _results(
        tmp_path / "fast", "diacc", [(0, 30.0, 1.0, 200, 0.0, 0.0), (1, 30.0, 1.0, 200, 0.0, 0.0)]
    )
    (fast / "meta.json").write_text(json.dumps({"policy": "diacc", "backend": "highway"}))
    table = build_table([hdv, diacc, fast])
    (cell,) = table.cells
    highway = next(c for c in table.columns if table.backend[c] == "highway")
    sumo = next(
        c for c in table.columns if table.backend[c] == "sumo" and table.policy[c] == "diacc"
    )
    assert table.best(cell, "speed") == {sumo}  # 30 m/s on highway does not beat sumo's 16
    assert table.change(cell, "speed", highway) is None  # no pure HDV on highway to compare
    assert table.reference(highway) is None
    assert any("within" in n or "one backend" in n for n in table.notes)


def _flow_results(path: Path, policy: str, speeds: list[float], delays: list[float]) -> Path:
    """Results of cell train-25 N25 rho0.4 D1 with the flow columns (100 samples, 0 std)."""
    path.mkdir(parents=True)
    (path / "meta.json").write_text(json.dumps({"policy": policy, "backend": "sumo"}))
    columns = [*COLUMNS, "throughput_vph", "delay_per_vehicle_s", "never_arrived_fraction"]
    with open(path / "episodes.csv", "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(columns)
        for ep, (speed, delay) in enumerate(zip(speeds, delays, strict=True)):
            base = [policy, "sumo", "", "paper", "train-25", 25, 0.4, "D1", ep]
            writer.writerow([*base, speed, 0.0, 100, 0.0, 0.0, 900.0, delay, "nan" if ep else 0.1])
    return path


def test_gains_against_same_mix_and_flow_rows(tmp_path, capsys):
    hdv = _flow_results(tmp_path / "hdv", "pure-hdv", [10.0, 10.0], [20.0, 20.0])
    mix = _flow_results(tmp_path / "mix", "same-mix", [12.5, 12.5], [10.0, 10.0])
    agent = _flow_results(tmp_path / "agent", "diacc", [11.0, 13.0], [8.0, 12.0])
    old = tmp_path / "old"  # written before the flow columns existed
    _results(old, "cooperative", [(0, 9.0, 0.0, 100, 0.0, 0.0)])
    table = build_table([hdv, mix, agent, old], rows=("speed", "throughput", "delay"))
    (cell,) = table.cells
    # diacc: speed 12 is +20% against pure HDV (10) and -4% against same-mix (12.5);
    # delay 10 s is -50% against pure HDV (20 s) and +0% against same-mix.
    assert table.change(cell, "speed", "diacc") == pytest.approx(20.0)
    assert table.change(cell, "speed", "diacc", "same-mix") == pytest.approx(-4.0)
    assert table.change(cell, "delay", "diacc", "same-mix") == pytest.approx(0.0)
    assert table.change(cell, "speed", "same-mix") == pytest.approx(25.0)
    assert table.change(cell, "speed", "same-mix", "same-mix") is None
    assert table.change(cell, "speed", "pure-hdv", "same-mix") is None
    assert (cell.key, "delay", "cooperative") not in table.stats  # old file: no flow row
    markdown = render_table(table, "markdown")
    assert "| _12.00 ± 1.00_ (+20.0 %, -4.0 %) | 9.00 ± 0.00 (-10.0 %, -28.0 %) |" in markdown
    assert "| Delay (s/veh) | _20.00 ± 0.00_ | **10.00 ± 0.00** (-50.0 %) |" in markdown
    assert "| Throughput (veh/h) | **900.00 ± 0.00** |" in markdown
    assert "against pure HDV and same-mix" in markdown
    csv_rows = list(csv.DictReader(io.StringIO(render_table(table, "csv"))))
    speed = {r["policy"]: r for r in csv_rows if r["metric"] == "speed"}
    assert float(speed["diacc"]["change_same_mix"]) == pytest.approx(-4.0)
    # never arrived: an episode's nan is left out (1 of 2 episodes defined)
    table = build_table([hdv], rows=("never_arrived",))
    stat = table.stats[(cell.key, "never_arrived", "pure-hdv")]
    assert (stat.mean, stat.n_episodes) == pytest.approx((10.0, 1))
    assert main(["table", str(hdv), str(agent), "--rows", "speed,flow"]) == 2  # no travel time
    assert "has the data of row 'arrived_speed'" in capsys.readouterr().err
