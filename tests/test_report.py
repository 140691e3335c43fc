"""`diacc table` on a tiny synthetic results set, against hand-computed numbers."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import pytest

from diacc.cli import main
from diacc.report import build_table, render_table

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
    #   relative change: speed (16-13)/13 = +23.1%, p(WE) (5-30)/30 = -83.3%, p(SCE) -100%
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
    assert table.relative_change(cell, "speed", "diacc") == pytest.approx(300 / 13)
    assert table.relative_change(cell, "p_we", "diacc") == pytest.approx(-250 / 3)
    assert table.relative_change(cell, "p_sce", "diacc") == pytest.approx(-100.0)
    assert table.relative_change(cell, "speed", "pure-hdv") is None
    assert table.best(cell, "speed") == {"diacc"} and table.best(cell, "p_sce") == {"diacc"}

    markdown = render_table(table, "markdown")
    assert (
        "| N=25, rho=0.4, D1 | Speed (m/s) | 13.00 ± 2.00 | **16.00 ± 1.41** (+23.1%) |" in markdown
    )
    assert "| p(WE) (%) | 30.00 ± 10.00 | **5.00 ± 5.00** (-83.3%) |" in markdown
    assert "| p(SCE) (%) | 8.00 ± 0.00 | **0.00 ± 0.00** (-100.0%) |" in markdown
    assert "SUMO 1.28.0, style preset paper, 2 episodes per cell" in markdown

    latex = render_table(table, "latex")
    assert r"\textbf{16.00 $\pm$ 1.41} (+23.1\%)" in latex and r"\multirow{3}{*}" in latex

    rows = list(csv.DictReader(io.StringIO(render_table(table, "csv"))))
    speed = {r["policy"]: r for r in rows if r["metric"] == "speed"}
    assert float(speed["diacc"]["rel_change_pct"]) == pytest.approx(300 / 13)
    assert speed["diacc"]["best"] == "1" and speed["pure-hdv"]["rel_change_pct"] == ""


def test_speed_std_over_episodes(results):
    table = build_table(list(results), speed_std="episodes")
    stat = table.stats[(table.cells[0].key, "speed", "pure-hdv")]
    assert (stat.mean, stat.std) == pytest.approx((12.0, 2.0))  # episode means 10 and 14


def test_table_cli_formats(results, tmp_path, capsys):
    assert main(["table", *map(str, results)]) == 0
    assert "**16.00 ± 1.41** (+23.1%)" in capsys.readouterr().out
    assert (
        main(["table", *map(str, results), "--format", "csv", "--out", str(tmp_path / "t.csv")])
        == 0
    )
    assert (tmp_path / "t.csv").read_text().startswith("map,n_vehicles")
