"""Paired changes against same-mix with bootstrap intervals (`diacc table`), on hand-made
episodes whose answers are known."""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import numpy as np
import pytest

from diacc.cli import main
from diacc.experiments.paired import EpisodeValues, paired_change
from diacc.experiments.report import NO_DIFFERENCE, build_table, render_table

COLUMNS = ["policy", "backend", "style_preset", "map", "n_vehicles", "cav_penetration"]
COLUMNS += ["style_mix", "stream", "episode", "seed", "mean_speed_mps", "std_speed_mps"]
COLUMNS += ["n_speed_samples", "p_we", "p_sce", "delay_per_vehicle_s", "collision"]


def _values(seeds, values) -> EpisodeValues:
    return EpisodeValues(
        np.array(seeds, dtype=np.int64), np.array(values, float), np.ones(len(seeds))
    )


def test_a_shift_on_every_pair_is_exact_however_noisy_the_traffic():
    """Pairing removes the traffic's spread: each episode 20 % less than its same-mix twin,
    over traffic from 5 to 50 s, is -20 % with a zero-width interval."""
    traffic = np.random.default_rng(1).uniform(5.0, 50.0, 30)
    ref = _values(range(30), traffic)
    agent = _values(range(30), 0.8 * traffic)
    change = paired_change(agent, ref, relative=True)
    assert change.n_pairs == 30 and change.measurable
    assert (change.change, change.low, change.high) == pytest.approx((-20.0, -20.0, -20.0))


def test_pairs_follow_seeds_not_order_and_skip_unmatched_or_undefined_episodes():
    ref = _values([11, 12, 13, 14], [1.0, 2.0, 3.0, 4.0])
    agent = _values([14, 12, 99, 13, 11], [6.0, 4.0, 100.0, np.nan, 3.0])  # +2 on each pair
    change = paired_change(agent, ref, relative=False)
    assert change.n_pairs == 3  # 99 has no twin, 13 is undefined
    assert (change.change, change.low, change.high) == pytest.approx((2.0, 2.0, 2.0))
    assert paired_change(_values([11], [1.0]), ref, relative=False) is None  # one pair
    assert paired_change(agent, _values([11, 12], [0.0, 0.0]), relative=True) is None  # / 0


def test_an_interval_that_holds_zero_is_no_measurable_difference_and_is_seeded():
    rng = np.random.default_rng(7)
    ref = _values(range(30), rng.normal(10.0, 3.0, 30))
    agent = _values(range(30), ref.value + rng.normal(0.0, 3.0, 30))  # noise, no effect
    change = paired_change(agent, ref, relative=False)
    assert change.low < 0.0 < change.high and not change.measurable
    assert change.low < change.change < change.high
    assert paired_change(agent, ref, relative=False) == change  # same files, same interval
    same = paired_change(ref, ref, relative=False)  # identical episodes: [0, 0] holds 0
    assert (same.low, same.high, same.measurable) == (0.0, 0.0, False)


def test_a_column_pooling_runs_pairs_every_run_and_resamples_the_runs():
    """Two training runs on the same 30 episode seeds, one 20 % below same-mix, one level:
    the pooled change is -10 %, and resampling the runs spreads it over [-20, 0] (pairing
    only one run's episode per seed would report -20 % [-20, -20])."""
    traffic = np.random.default_rng(3).uniform(5.0, 50.0, 30)
    ref = _values(range(30), traffic)
    seeds = np.tile(np.arange(30), 2)  # (60,): run 0's episodes, then run 1's
    pooled = EpisodeValues(
        seeds, np.concatenate([0.8 * traffic, traffic]), np.ones(60), np.repeat([0, 1], 30)
    )
    change = paired_change(pooled, ref, relative=True)
    assert change.n_pairs == 30  # episode seeds
    assert change.change == pytest.approx(-10.0)
    assert (change.low, change.high) == pytest.approx((-20.0, 0.0))
    assert not change.measurable
    one_run = EpisodeValues(seeds[:30], 0.8 * traffic, np.ones(30), np.zeros(30, np.int64))
    assert paired_change(one_run, ref, relative=True) == paired_change(
        _values(range(30), 0.8 * traffic), ref, relative=True
    )


def _results(
    path: Path, policy: str, delays: list[float], p_sce: list[float], maps=("train-50",)
) -> Path:
    path.mkdir(parents=True)
    (path / "meta.json").write_text(json.dumps({"policy": policy, "backend": "highway"}))
    with open(path / "episodes.csv", "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(COLUMNS)
        for map_name in maps:
            for ep, (delay, sce) in enumerate(zip(delays, p_sce, strict=True)):
                row = [policy, "highway", "realistic", map_name, 25, 0.4, "D1", "test", ep]
                writer.writerow([*row, 1000 + 2 * ep + 1, 20.0, 1.0, 100, 0.0, sce, delay, 0])
    return path


def test_table_shows_the_interval_and_marks_no_measurable_difference(tmp_path):
    traffic = [10.0, 14.0, 12.0, 16.0]
    mix = _results(tmp_path / "mix", "same-mix", traffic, [0.1, 0.0, 0.2, 0.1])
    agent = _results(tmp_path / "agent", "diacc", [0.75 * d for d in traffic], [0.0, 0.1, 0.2, 0.1])
    table = build_table([mix, agent], rows=("delay", "p_sce"))
    markdown = render_table(table, "markdown")
    # delay: -25 % on every pair; p(SCE): -10, +10, 0, 0 pp, an interval around 0
    assert "(-25.0 % [-25.0, -25.0])" in markdown
    assert f"({NO_DIFFERENCE} +0.0 pp [-7.5, +7.5])" in markdown  # means of 4 resampled
    assert "no measurable difference" in markdown and "seed stream test" in markdown
    rows = list(csv.DictReader(io.StringIO(render_table(table, "csv"))))
    (delay,) = [r for r in rows if r["metric"] == "delay" and r["policy"] == "diacc"]
    assert float(delay["ci_low"]) == pytest.approx(-25.0)
    assert (delay["paired_against"], delay["n_pairs"], delay["measurable"]) == (
        "same-mix",
        "4",
        "1",
    )
    (sce,) = [r for r in rows if r["metric"] == "p_sce" and r["policy"] == "diacc"]
    assert sce["measurable"] == "0"
    assert "$\\approx$" in render_table(table, "latex")


def test_paired_against_another_column(tmp_path, capsys):
    """`--paired-against heuristic`: is the agent better than the rule on the same traffic?"""
    traffic = [10.0, 14.0, 12.0, 16.0]
    dirs = [
        _results(tmp_path / "mix", "same-mix", traffic, [0.1] * 4),
        _results(tmp_path / "rule", "heuristic", [0.9 * d for d in traffic], [0.1] * 4),
        _results(tmp_path / "agent", "diacc", [0.72 * d for d in traffic], [0.1] * 4),
    ]
    table = build_table(dirs, rows=("delay",), paired_against="heuristic")
    markdown = render_table(table, "markdown")
    assert "(-28.0 %, vs heuristic -20.0 % [-20.0, -20.0])" in markdown  # 0.72 / 0.9
    assert "change against heuristic" in markdown
    argv = ["table", *map(str, dirs), "--rows", "delay", "--paired-against", "cooperative"]
    assert main(argv) == 2
    assert "--paired-against cooperative: neither a policy" in capsys.readouterr().err


def test_paired_against_a_results_directory(tmp_path):
    """Two checkpoints share the policy name ``diacc``: pair one with the other by directory."""
    traffic = [10.0, 14.0, 12.0, 16.0]
    dirs = [
        _results(tmp_path / "mix", "same-mix", traffic, [0.1] * 4),
        _results(tmp_path / "source", "diacc", [0.8 * d for d in traffic], [0.1] * 4),
        _results(tmp_path / "tuned", "diacc", [0.6 * d for d in traffic], [0.1] * 4),
    ]
    table = build_table(dirs, rows=("delay",), paired_against=str(dirs[1]))
    source, tuned = table.columns[1], table.columns[2]
    assert table.paired_against == source
    cell = table.cells[0]
    change = table.paired(cell, "delay", tuned)
    assert (change.change, change.low, change.high) == pytest.approx((-25.0, -25.0, -25.0))
    assert table.paired(cell, "delay", source) is None  # the reference itself
    assert f"vs {source} -25.0 % [-25.0, -25.0]" in render_table(table, "markdown")


def test_reproduce_tables_pool_the_seeds_of_a_variant_in_the_intervals(tmp_path):
    """`diacc reproduce` pools seeds 1 and 2 of diacc into one column: both runs' episodes
    pair with same-mix (here -30 % and -10 %: -20 % pooled, between-seed spread in the
    interval)."""
    from diacc.experiments.report import table_from_results
    from diacc.experiments.reproduce.outputs import BASELINE_COLUMNS, _columns, _Results
    from diacc.experiments.reproduce.plan import make_plan, resolve_config

    plan = make_plan(*resolve_config("tiny", out_dir=tmp_path, seeds=(1, 2), variants=("diacc",)))
    traffic = [10.0, 14.0, 12.0, 16.0]
    shares = dict.fromkeys(BASELINE_COLUMNS, 1.0) | {
        "diacc-train-50-s1": 0.7,
        "diacc-train-50-s2": 0.9,
    }
    for policy, share in shares.items():
        _results(
            tmp_path / "eval/highway" / policy, policy, [share * d for d in traffic], [0.1] * 4
        )
    columns = _columns(plan, _Results(plan), "highway", plan.grid_cells["train"])
    columns = [c for c in columns if c[1]["policy"] in ("same-mix", "pure-hdv", "diacc")]
    table = table_from_results(columns, rows=("delay",))
    change = table.paired(table.cells[0], "delay", "diacc")
    assert change.n_pairs == 4 and change.change == pytest.approx(-20.0)
    assert (change.low, change.high) == pytest.approx((-30.0, -10.0))


def test_study_compare_script_pools_seeds_per_setting(tmp_path):
    """benchmarks/studies/paper-convergence/compare.py on a study's layout: each setting
    pools its seeds (of one map), per-seed changes beside, any learned column as the
    reference."""
    import subprocess
    import sys

    traffic = [10.0, 14.0, 12.0, 16.0]
    shares = {"pure-hdv": 1.1, "same-mix": 1.0, "cooperative": 1.0, "heuristic": 0.9}
    shares |= {"diacc-train-50-s1-tau_init2": 0.7, "diacc-train-50-s2-tau_init2": 0.9}
    shares |= {"diacc-train-50-s1-tau_init10": 0.8, "diacc-train-50-s2-tau_init10": 0.8}
    shares |= {"diacc-train-25-s1-tau_init2": 0.5}  # the other map's run: a column of its own
    for policy, share in shares.items():
        _results(
            tmp_path / "eval/highway" / policy, policy, [share * d for d in traffic], [0.1] * 4
        )
    run = tmp_path / "runs/diacc-train-50-s1-tau_init2"
    run.mkdir(parents=True)
    records = [(50_000, 30.0), (100_000, 20.0), (150_000, 18.0)]  # the last 100k: 19.0
    run.joinpath("progress.jsonl").write_text(
        "".join(
            json.dumps({"update": k, "global_step": step, "episode/delay_per_vehicle_s": delay})
            + "\n"
            for k, (step, delay) in enumerate(records, 1)
        )
    )
    script = Path(__file__).parents[1] / "benchmarks/studies/paper-convergence/compare.py"
    argv = [sys.executable, str(script), str(tmp_path), "--against", "diacc-tau_init10"]
    out = subprocess.run(
        [*argv, "--last-steps", "100000"], capture_output=True, text=True, check=True
    ).stdout
    assert "- diacc-tau_init2: s1 19.0 @ 150k\n" in out
    (row,) = [line for line in out.splitlines() if line.startswith("| diacc-tau_init2 |")]
    entries = [e.strip() for e in row.strip("|").split("|")]
    assert entries[1] == "-20.0 [-30.0, -10.0]"  # vs same-mix: seeds at -30 % and -10 %
    assert entries[3] == "≈ +0.0 [-12.5, +12.5]"  # vs tau_init10 (-20 %): 0.7 or 0.9 of 0.8
    assert entries[4] == "s1 -30.0 [-30.0, -30.0], s2 -10.0 [-10.0, -10.0]"
    assert entries[5] == "0 % of 8"
    (other_map,) = [line for line in out.splitlines() if line.startswith("| diacc-tau_init2@")]
    assert other_map.startswith("| diacc-tau_init2@train-25 | -50.0 [-50.0, -50.0] |")
    bad = subprocess.run([*argv[:3], "--against", "mappo"], capture_output=True, text=True)
    assert bad.returncode == 2 and "--against mappo: not a learned column" in bad.stderr
    run.joinpath("progress.jsonl").write_text("{not json\n")
    broken = subprocess.run(argv, capture_output=True, text=True)
    assert broken.returncode == 1 and broken.stderr.startswith("compare.py: error: ")
    assert "Traceback" not in broken.stderr


def test_compare_script_pairs_each_map_with_its_own_mappo_iadm(tmp_path):
    """Without --against, compare.py pairs every column with the mappo-iadm column of each
    map; a column of the other map, which never played the cell, shows "—"."""
    import subprocess
    import sys

    traffic = [10.0, 14.0, 12.0, 16.0]
    plays = {"diacc-train-25-s1": 0.6, "mappo-iadm-train-25-s1": 0.8}
    both = ("train-25", "train-50")
    for name in ("pure-hdv", "same-mix", "cooperative", "heuristic"):
        _results(tmp_path / "eval/highway" / name, name, traffic, [0.1] * 4, both)
    for policy, share in plays.items():
        delays = [share * d for d in traffic]
        _results(tmp_path / "eval/highway" / policy, policy, delays, [0.1] * 4, ("train-25",))
    _results(tmp_path / "eval/highway/mappo-iadm-train-50-s1", "mappo-iadm", traffic, [0.1] * 4)
    script = Path(__file__).parents[1] / "benchmarks/studies/paper-convergence/compare.py"
    out = subprocess.run(
        [sys.executable, str(script), str(tmp_path)], capture_output=True, text=True, check=True
    ).stdout
    assert "| vs same-mix | vs heuristic | vs mappo-iadm@train-25 | vs mappo-iadm |" in out
    (row,) = [line for line in out.splitlines() if line.startswith("| diacc@train-25 |")]
    entries = [e.strip() for e in row.strip("|").split("|")]
    assert entries[1:3] == ["-40.0 [-40.0, -40.0]"] * 2  # vs same-mix and the heuristic
    assert entries[3:5] == ["-25.0 [-25.0, -25.0]", "—"]  # 0.6 of 0.8; train-50's never met
    argv = [sys.executable, str(script), str(tmp_path), "--against", "pure-hdv"]
    out = subprocess.run(argv, capture_output=True, text=True, check=True).stdout
    assert "| vs same-mix | vs heuristic | vs pure-hdv | vs same-mix, per seed |" in out
