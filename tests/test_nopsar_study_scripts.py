"""The no-PSAR study's scripts. dense_rows.py: the per-seed and pooled comparison of
the dense zero-shot rows (issue 60 item 4) pairs episodes by row and episode number,
counts collisions per row, and marks a change whose interval holds 0; situation_probe.py
files each decision under its situation."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks/studies/nopsar-learning/dense_rows.py"
FIELDS = ["map", "n_vehicles", "cav_penetration", "style_mix", "episode", "seed"]
FIELDS += ["delay_per_vehicle_s", "mean_speed_mps", "collision"]


def _write(folder: Path, delay_s: dict[int, list[float]], crash_in: tuple[int, ...] = ()) -> None:
    """One evaluation: per row N (30 or 40) the episodes' delays; the same episode seed
    in both rows, as a stream gives episode i one seed."""
    folder.mkdir(parents=True)
    with (folder / "episodes.csv").open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(FIELDS)
        for n, delays in delay_s.items():
            for episode, delay in enumerate(delays):
                crashed = int(n == 40 and episode in crash_in)
                row = [
                    "test-50",
                    n,
                    0.2,
                    "D1",
                    episode,
                    1000 + episode,
                    delay,
                    300 / delay,
                    crashed,
                ]
                writer.writerow(row)


def test_dense_rows_pairs_by_row_and_episode(tmp_path):
    arm = tmp_path / "arm" / "eval"
    ref = tmp_path / "reference" / "eval"
    base = [10.0, 12.0, 11.0, 13.0, 9.0, 10.5]
    for backend in ("highway", "sumo"):
        _write(ref / f"test-{backend}-dense/same-mix", {30: base, 40: [d + 5 for d in base]})
        _write(ref / f"test-{backend}-dense/heuristic", {30: base, 40: base})
        # diacc-nopsar 2 s faster than same-mix on every episode of both rows; mappo level
        # with the heuristic on N = 30 (episodes shuffled by +-0.1 around it)
        for seed in (1, 2):
            faster = {30: [d - 2 for d in base], 40: [d + 3 for d in base]}
            _write(arm / f"test-{backend}-dense/diacc-nopsar-s{seed}", faster, crash_in=(0,))
        wobble = [d + (0.1 if i % 2 else -0.1) for i, d in enumerate(base)]
        _write(arm / f"test-{backend}-dense/mappo-s1", {30: wobble, 40: wobble})
    out = subprocess.run(
        [sys.executable, str(SCRIPT), "--arm", "arm", "--results", str(tmp_path)],
        capture_output=True, text=True, check=True,
    ).stdout  # fmt: skip
    lines = out.splitlines()
    n30 = "| test-50 N = 30, rho = 0.2 | highway | diacc-nopsar-s1 | 0 of 6 | 8.92 | -2.00 [-2.00,"
    assert any(line.startswith(n30) for line in lines), out
    n40 = "| test-50 N = 40, rho = 0.2 | sumo | diacc-nopsar-s2 | 1 of 6 | 13.92 | -2.00"
    assert any(line.startswith(n40) for line in lines), out
    mappo = next(line for line in lines if "N = 30" in line and "highway | mappo-s1" in line)
    assert mappo.split("|")[7].strip().startswith("≈")  # level with the heuristic
    pooled = [line for line in lines if "| 2 / 1 |" in line]
    assert len(pooled) == 4  # two rows x two simulators
    assert "-2.00 [" in pooled[0] and "%" in pooled[0]


def test_situation_probe_files_every_decision_under_one_situation_of_each_kind():
    """situation_probe.py (the same study): the heuristic's decisions, each filed once under
    a following situation and once under a lane situation, and its rule shows: where its
    lane ends within 300 m it moves right or keeps to its lane, never accelerates."""
    script = SCRIPT.with_name("situation_probe.py")
    out = subprocess.run(
        [sys.executable, str(script), "heuristic", "--episodes", "1", "--episode-steps", "40"],
        capture_output=True, text=True, check=True,
    ).stdout  # fmt: skip
    rows = [line.split("|")[1:-1] for line in out.splitlines() if line.startswith("| ")]
    rows = [[cell.strip() for cell in row] for row in rows if row[0].strip() != "situation"]
    following = [r for r in rows if r[0].startswith(("gap", "no vehicle"))]
    lane = [r for r in rows if r[0].startswith("its lane")]
    assert following and lane and len(following) + len(lane) == len(rows)
    for kind in (following, lane):
        assert abs(sum(int(r[1].rstrip("%")) for r in kind) - 100) <= len(kind)  # rounding
        for r in kind:  # each row's action shares add up to 100 % too
            assert abs(sum(int(c.rstrip("%")) for c in r[2:]) - 100) <= 5
    near_end = [r for r in lane if r[0] == "its lane ends < 300 m ahead"]
    assert not near_end or near_end[0][5] == "0%"  # accelerate, the 4th action


def test_situation_probe_plays_the_training_traffic_on_another_road():
    """``--map``: the same traffic on another road (issue 60: why a seed stalls on a
    generated road whose lanes narrow to one), named in each table's title."""
    script = SCRIPT.with_name("situation_probe.py")
    out = subprocess.run(
        [sys.executable, str(script), "heuristic", "--episodes", "1", "--episode-steps", "20",
         "--map", "gen-validation-17"],
        capture_output=True, text=True, check=True,
    ).stdout  # fmt: skip
    assert "heuristic (gen-validation-17) on highway:" in out
    assert any(line.startswith("| its lane") for line in out.splitlines())
