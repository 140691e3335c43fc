"""`diacc reproduce`: the whole pipeline at the tiny budget, resuming, and bad input.

The tiny reproduction runs once per module (about 30 s on an idle 2-core
machine): one of its runs is interrupted beforehand, so the first invocation
has to resume it; later tests re-run the command on its files (a finished
reproduction is only checked; a deleted evaluation cell is recomputed, and
comes out the same). Numbers in the tables and the transfer report are
checked against the evaluation files they are computed from.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import io
import json
import os
import re
import time
from pathlib import Path

import pytest

from diacc.cli import main
from diacc.experiments.reproduce.plan import BUDGETS, grid_cells, make_plan, resolve_config
from diacc.experiments.reproduce.stages import row_cell_key

TINY = ["reproduce", "--budget", "tiny", "--no-progress"]
#: What the tiny budget writes besides runs/ and eval/.
TINY_OUTPUTS = [
    "tables/table2.md",
    "tables/table2.tex",
    "tables/table3.md",
    "tables/table3.tex",
    "figures/curves-train-50.png",
    "figures/curves-train-50.pdf",
    "figures/speeds-highway-train-50.png",
    "figures/speeds-sumo-train-50.png",
    "figures/speeds-highway-test-50.png",
    "figures/speeds-sumo-test-50.png",
    "transfer.md",
    "transfer.csv",
    "manifest.json",
]
TRAIN_CELL = "train-50_N25_rho0.40_D1"


def _episodes(path: Path) -> list[dict[str, str]]:
    with open(path / "episodes.csv", newline="") as fh:
        return list(csv.DictReader(fh))


def _pooled_speed(rows: list[dict[str, str]], cell_key: str) -> float:
    """Mean speed over all vehicle-steps of a cell's episodes (as the tables define it)."""
    mine = [r for r in rows if row_cell_key(r) == cell_key]
    assert mine, f"no rows of {cell_key}"
    n = [int(r["n_speed_samples"]) for r in mine]
    return sum(k * float(r["mean_speed_mps"]) for k, r in zip(n, mine, strict=True)) / sum(n)


def _table_speed(markdown: str, backend: str, column: str) -> float:
    """The speed mean of ``column`` in the first cell of a backend's section of a table."""
    section = markdown.split(f"## {backend} backend", 1)[1].split("## ", 1)[0]
    lines = [line for line in section.splitlines() if line.startswith("|")]
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    speed = next(line for line in lines if "Speed (m/s)" in line)
    entry = [c.strip() for c in speed.strip("|").split("|")][header.index(column)]
    return float(re.search(r"(-?\d+\.\d+) ±", entry).group(1))


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A finished tiny reproduction whose diacc run was interrupted once; (out, stdout)."""
    from diacc.learn.mappo import train

    out = tmp_path_factory.mktemp("reproduce") / "tiny"
    config, notes = resolve_config("tiny", out_dir=out)
    plan = make_plan(config, notes)
    run = next(r for r in plan.runs if r.name == "diacc-train-50-s1")
    train(plan.train_config(run), progress=False, stop_after_updates=1)  # killed after update 1
    stdout = io.StringIO()
    start = time.perf_counter()
    with contextlib.redirect_stdout(stdout):
        assert main([*TINY, "--out", str(out)]) == 0
    print(f"tiny reproduction: {time.perf_counter() - start:.1f} s")
    return out, stdout.getvalue()


def test_tiny_budget_writes_every_output(tiny):
    out, stdout = tiny
    for rel in TINY_OUTPUTS:
        assert (out / rel).is_file(), rel
    assert (
        "training: 5 runs = 4 variants x 1 map x 1 seed on highway + 1 for the transfer" in stdout
    )
    assert "[4/5] resumed diacc-train-50-s1" in stdout  # the interrupted run continued
    assert "[1/5] trained mappo-train-50-s1" in stdout
    assert "[17/17] eval diacc-train-50-s1-sumo on sumo: 1 of 1 cells to run" in stdout
    assert f"  [17/17] cell [1/1] {TRAIN_CELL}: mean speed " in stdout
    manifest = json.loads((out / "manifest.json").read_text())
    assert all(stage["finished"] for stage in manifest["stages"].values())
    assert manifest["invocations"][-1]["exit"] == "finished"
    assert manifest["config"]["budget"]["steps_per_run"] == 200
    assert manifest["versions"]["torch"] and manifest["seeds"] == [1]
    assert manifest["stages"]["train"]["env_steps"]["diacc-train-50-s1"] == 200
    for rel in (
        "runs/diacc-train-50-s1/checkpoint.pt",
        "runs/diacc-train-50-s1-sumo/checkpoint.pt",
    ):
        assert (out / rel).is_file()


def test_table_numbers_come_from_the_evaluation_files(tiny):
    out, _ = tiny
    table2 = (out / "tables/table2.md").read_text()
    table3 = (out / "tables/table3.md").read_text()
    for backend in ("highway", "sumo"):
        for column, policy in (("pure-hdv", "pure-hdv"), ("diacc", "diacc-train-50-s1")):
            rows = _episodes(out / "eval" / backend / policy)
            expected = _pooled_speed(rows, TRAIN_CELL)
            assert _table_speed(table2, backend, column) == pytest.approx(expected, abs=0.006)
            zero_shot = grid_cells("zero-shot", ("train-50",), 1)[0].key
            expected = _pooled_speed(rows, zero_shot)
            assert _table_speed(table3, backend, column) == pytest.approx(expected, abs=0.006)
    assert "test-50" in table3 and "train-50" not in table3.split("**", 2)[1]
    assert "| pure-hdv | same-mix | cooperative | heuristic | " in table2
    assert "| Delay (s/veh) |" in table2 and "against pure HDV and same-mix" in table2
    assert "\\begin{tabular}" in (out / "tables/table2.tex").read_text()


def test_transfer_report_comes_from_sumo_evaluations(tiny):
    out, _ = tiny
    with open(out / "transfer.csv", newline="") as fh:
        (row,) = list(csv.DictReader(fh))
    hdv = _pooled_speed(_episodes(out / "eval/sumo/pure-hdv"), TRAIN_CELL)
    source = _pooled_speed(_episodes(out / "eval/sumo/diacc-train-50-s1"), TRAIN_CELL)
    target = _pooled_speed(_episodes(out / "eval/sumo/diacc-train-50-s1-sumo"), TRAIN_CELL)
    assert float(row["pure_hdv_speed_mps"]) == pytest.approx(hdv)
    assert float(row["highway_trained_speed_mps"]) == pytest.approx(source)
    assert float(row["sumo_trained_speed_mps"]) == pytest.approx(target)
    assert float(row["sumo_trained_gain_mps"]) == pytest.approx(target - hdv)
    text = (out / "transfer.md").read_text()
    if target - hdv > 0:
        assert float(row["kept_share"]) == pytest.approx((source - hdv) / (target - hdv))
    else:
        assert row["kept_share"] == "n/a"
        assert "kept share n/a because the sumo-trained policy is not faster" in text
    assert f"| {TRAIN_CELL} | {hdv:.2f} |" in text


def test_second_invocation_only_checks(tiny, capsys):
    out, _ = tiny
    before = {rel: (out / rel).stat().st_mtime_ns for rel in TINY_OUTPUTS[:-1]}
    start = time.perf_counter()
    assert main([*TINY, "--out", str(out)]) == 0
    seconds = time.perf_counter() - start
    stdout = capsys.readouterr().out
    assert stdout.count("skipped") == 5 and "trained" not in stdout.replace("trained on", "")
    assert stdout.count("cells already done") == 17 and "cells to run" not in stdout
    assert "outputs were up to date" in stdout
    assert before == {rel: (out / rel).stat().st_mtime_ns for rel in before}
    assert seconds < 60  # a few seconds on an idle machine: nothing is loaded or simulated
    manifest = json.loads((out / "manifest.json").read_text())
    assert len(manifest["invocations"]) == 2


def test_deleted_cell_is_recomputed_and_equal(tiny, capsys):
    out, _ = tiny
    job = out / "eval/sumo/mappo-train-50-s1"
    before = _pooled_speed(_episodes(job), TRAIN_CELL)
    (job / "cells" / f"{TRAIN_CELL}.episodes.csv").unlink()
    assert main([*TINY, "--out", str(out)]) == 0
    stdout = capsys.readouterr().out
    assert "eval mappo-train-50-s1 on sumo: 1 of 2 cells to run" in stdout
    assert stdout.count("cells to run") == 1 and stdout.count(" cell [") == 1
    assert _pooled_speed(_episodes(job), TRAIN_CELL) == before  # seeded: the same episode


def test_merge_cut_short_is_redone(tiny, capsys):
    """A kill between the merged episodes file and the merged speeds file (found by the slow
    kill test): the job is merged again instead of being taken as done."""
    out, _ = tiny
    job = out / "eval/highway/pure-hdv"
    speeds = (job / "speeds.csv.gz").read_bytes()
    (job / "speeds.csv.gz").unlink()
    assert main([*TINY, "--out", str(out)]) == 0
    assert "eval pure-hdv on highway: 0 of 2 cells to run" in capsys.readouterr().out
    assert (job / "speeds.csv.gz").read_bytes() == speeds
    os.utime(job / "speeds.csv.gz", ns=(1, 1))  # older than episodes.csv: merge cut short
    assert main([*TINY, "--out", str(out)]) == 0
    assert "eval pure-hdv on highway: 0 of 2 cells to run" in capsys.readouterr().out


def test_other_settings_into_the_same_folder_are_refused(tiny, capsys):
    out, _ = tiny
    before = (out / "manifest.json").read_text()
    assert main([*TINY, "--out", str(out), "--envs", "2"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("diacc: error: ") and "was trained with another n_envs" in err
    assert "\n" not in err and (out / "manifest.json").read_text() == before


def test_sampled_actions_evaluate_the_same_checkpoints(tiny, tmp_path, capsys):
    """``--actions sampled`` on copied runs: nothing retrained, learned columns sampled.

    Into the greedy reproduction's own folder it is refused (its evaluations
    hold greedy results).
    """
    import shutil

    out, _ = tiny
    assert main([*TINY, "--out", str(out), "--actions", "sampled"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("diacc: error: ") and "\n" not in err
    assert "another actions ('greedy'" in err
    assert main([*TINY, "--out", str(out), "--episode-steps", "50"]) == 2
    assert "another settings" in capsys.readouterr().err
    sampled = tmp_path / "sampled"
    shutil.copytree(out / "runs", sampled / "runs")
    assert main([*TINY, "--out", str(sampled), "--actions", "sampled"]) == 0
    stdout = capsys.readouterr().out
    assert "checkpoints act sampled" in stdout and "] trained " not in stdout
    for meta_path in (sampled / "eval").glob("*/*/meta.json"):
        meta = json.loads(meta_path.read_text())
        assert meta.get("actions", "none") == ("sampled" if "checkpoint" in meta else "none")
    assert "sampled actions" in (sampled / "tables" / "table2.md").read_text()


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--budget", "huge"], "unknown budget 'huge'; use one of tiny, small, paper"),
        (["--variants", "diacc,nope"], "unknown variant 'nope'"),
        (["--maps", "nowhere"], "unknown map 'nowhere'"),
        (["--backends", "highway,carla"], "unknown backend 'carla'"),
        (["--train-backend", "carla"], "unknown training backend 'carla'"),
        (["--grids", "zeroshot"], "unknown grid 'zeroshot'"),
        (["--seeds", "1,x"], "comma-separated list of int"),
        (["--seeds", "1,1"], "--seeds names a value twice"),
        (["--steps", "0"], "--steps must be >= 1"),
        (["--style-preset", "wild"], "unknown style preset 'wild'"),
        (["--jobs", "0"], "--jobs must be in [1, 64], got 0"),
        (["--set", "nope=1"], "nope"),
        (["--transfer", "--train-backend", "sumo"], "needs --train-backend highway"),
        (["--sweep", "env.reward.nope=1,2"], "unknown config key 'env.reward.nope'"),
        (["--sweep", "env.reward.tau_final="], "the value list is empty"),
        (["--sweep", "env.reward.tau_final=0.1,abc"], "expects float, got 'abc'"),
        (["--sweep", "env.reward.tau_final=0.1,-1"], "must be > 0, got -1.0"),
        (["--study", "lambda"], "unknown study 'lambda'"),
    ],
)
def test_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys, extra, message):
    out = tmp_path / "out"
    assert main(["reproduce", "--budget", "tiny", "--out", str(out), *extra]) == 2
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert err.startswith("diacc: error: ") and message in err and "\n" not in err, err
    assert "Traceback" not in captured.err and not out.exists()


def test_budget_presets_and_overrides():
    config, _ = resolve_config("paper", steps=1000, seeds=(4, 5))
    assert config.budget.steps_per_run == 1000 and config.budget.seeds == (4, 5)
    assert config.budget.n_envs == 20 and config.budget.episodes_per_cell == 10  # kept
    assert config.budget.name == "paper (with overrides)"
    assert BUDGETS["paper"].steps_per_run == 3_000_000 and BUDGETS["paper"].seeds == (1, 2, 3)
    plan = make_plan(resolve_config("paper")[0])
    assert len(plan.runs) == 4 * 2 * 3 + 2 * 3  # + diacc on sumo per map and seed
    # seed-major: every variant and map of seed 1 comes before any run of seed 2
    seeds = [r.seed for r in plan.runs[: 4 * 2 * 3]]
    assert seeds == sorted(seeds) and [r.variant for r in plan.runs[:4]] == list(
        resolve_config("paper")[0].variants
    )
    assert set(plan.grid_cells) == {"train", "zero-shot"}  # the paper's cells by default
    assert len(plan.grid_cells["zero-shot"]) == 10 and len(plan.grid_cells["train"]) == 2
    # a checkpoint plays the cells of its map's lane reduction only
    job = next(j for j in plan.jobs if j.policy == "mappo-train-25-s1" and j.backend == "sumo")
    assert {c.map for c in job.cells} == {"train-25", "test-25"} and len(job.cells) == 6
    baseline = next(j for j in plan.jobs if j.policy == "pure-hdv" and j.backend == "highway")
    assert len(baseline.cells) == 12
    plan = make_plan(resolve_config("paper", grids=("train", "zero-shot-product"))[0])
    assert len(plan.grid_cells["zero-shot-product"]) == 32
    # the style preset reaches the training config (and, through EvalSettings, evaluation)
    plan = make_plan(resolve_config("tiny", style_preset="paper-congestion")[0])
    cfg = plan.train_config(plan.runs[0])
    assert '"style_preset": "paper-congestion"' in json.dumps(dataclasses.asdict(cfg))
    assert cfg.total_steps == 200 and cfg.n_envs == 1 and cfg.env.map == "train-50"


def test_sumo_training_turns_the_default_transfer_off_and_says_so(capsys):
    assert main(["reproduce", "--budget", "tiny", "--train-backend", "sumo", "--dry-run"]) == 0
    stdout = capsys.readouterr().out
    assert "transfer off" in stdout and "the training backend is sumo already" in stdout
    assert "training: 4 runs" in stdout


def test_zero_shot_cells_are_spread_over_each_test_map():
    cells = grid_cells("zero-shot", ("train-25", "train-50"), 2)
    assert [c.map for c in cells] == ["test-25", "test-25", "test-50", "test-50"]
    every = grid_cells("zero-shot", ("train-25", "train-50"))
    assert cells[1] == every[2] and len(every) == 10
    cells = grid_cells("zero-shot-product", ("train-25", "train-50"), 2)
    every = grid_cells("zero-shot-product", ("train-25", "train-50"))
    assert cells[1] == every[8] and len(every) == 32


def test_sweep_gives_each_setting_its_runs_columns_and_curves(tmp_path, capsys):
    """--study tau in the plan (dry run): one run per setting and seed, named by the setting;
    no transfer (it would compare settings with a default run)."""
    argv = ["reproduce", "--budget", "tiny", "--variants", "diacc", "--study", "tau"]
    assert main([*argv, "--out", str(tmp_path / "r"), "--dry-run"]) == 0
    stdout = capsys.readouterr().out
    assert "training: 4 runs = 1 variant x 1 map x 4 settings x 1 seed" in stdout
    assert "setting tau_init=10, tau_final=10" in stdout and "transfer off" in stdout
    assert "seed stream validation" in stdout  # a sweep chooses: never on test episodes
    assert main(["reproduce", "--budget", "tiny", "--dry-run"]) == 0
    assert "seed stream test" in capsys.readouterr().out
    config, notes = resolve_config("tiny", variants=("diacc",))
    from diacc.experiments.sweepaxes import sweep_settings

    plan = make_plan(config, notes)
    settings = sweep_settings(plan.train_config(plan.runs[0]), ["env.reward.tau_final=0.05,0.5"])
    plan = make_plan(dataclasses.replace(config, settings=tuple(settings)), notes)
    assert [r.name for r in plan.runs] == [
        "diacc-train-50-s1-tau_final0.05",
        "diacc-train-50-s1-tau_final0.5",
    ]
    assert [r.column for r in plan.runs] == ["diacc tau_final=0.05", "diacc tau_final=0.5"]
    assert [plan.train_config(r).env.reward.tau_final for r in plan.runs] == [0.05, 0.5]
    assert {j.policy for j in plan.jobs} >= {r.name for r in plan.runs}
    from diacc.experiments.reproduce.outputs import _learned_columns

    columns = _learned_columns(plan)  # one table column per setting, never pooled
    assert {label: [n for n, _ in members] for label, members in columns.items()} == {
        "diacc tau_final=0.05": ["diacc-train-50-s1-tau_final0.05"],
        "diacc tau_final=0.5": ["diacc-train-50-s1-tau_final0.5"],
    }


@pytest.mark.slow
def test_killed_reproduction_resumes_with_parallel_jobs(tmp_path):
    """Two seeds, both maps, 2 local jobs; killed during evaluation, then resumed;
    then a longer budget re-trains and re-evaluates every checkpoint."""
    import signal
    import subprocess
    import sys

    out = tmp_path / "r"
    argv = [sys.executable, "-m", "diacc.cli", *TINY, "--out", str(out), "--seeds", "1,2"]
    argv += ["--maps", "train-25,train-50", "--jobs", "2"]
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    proc = subprocess.Popen(
        argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
    )
    deadline = time.time() + 600
    while not list(out.glob("eval/*/*/cells/*.episodes.csv")) and time.time() < deadline:
        time.sleep(0.5)
    os.killpg(proc.pid, signal.SIGKILL)  # the command and its workers, as a crash would
    proc.wait()
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["stages"]["train"]["finished"] and not manifest["stages"]["eval"]["finished"]
    done = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=1200)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.count("skipped") == 20  # 16 runs + 4 transfer runs were finished
    partial = [
        int(k) < int(m) for k, m in re.findall(r"done, (\d+) of (\d+) cells run", done.stdout)
    ]
    assert "cells already done" in done.stdout or any(partial)  # finished cells were kept
    table2 = (out / "tables/table2.md").read_text()
    assert "train-25" in table2 and "train-50" in table2 and "pool 2 seed(s)" in table2
    with open(out / "transfer.csv", newline="") as fh:
        assert len(list(csv.DictReader(fh))) == 2
    longer = subprocess.run([*argv, "--steps", "300"], env=env, capture_output=True, text=True)
    assert longer.returncode == 0, longer.stderr[-2000:]
    assert longer.stdout.count("resumed") == 20
    assert "results of the checkpoint at 200 steps removed; it has 300 now" in longer.stdout
    assert "cells already done" in longer.stdout  # baselines are kept


@pytest.mark.slow
def test_ray_engine_gives_the_local_results(tmp_path, capsys):
    """Training runs and evaluation cells as Ray tasks on a local 2-CPU instance."""
    pytest.importorskip("ray")
    small = [*TINY, "--variants", "mappo,diacc", "--backends", "highway", "--no-transfer"]
    assert main([*small, "--out", str(tmp_path / "local")]) == 0
    ray_argv = [*small, "--out", str(tmp_path / "ray"), "--engine", "ray", "--ray-cpus", "2"]
    try:
        assert main(ray_argv) == 0
    finally:
        import ray

        ray.shutdown()
    stdout = capsys.readouterr().out
    # 2 runs; 6 eval jobs: the four baselines and the two checkpoints
    assert "[2/2] trained" in stdout and "[6/6] eval" in stdout
    for policy in ("pure-hdv", "mappo-train-50-s1", "diacc-train-50-s1"):
        local = _episodes(tmp_path / "local/eval/highway" / policy)
        remote = _episodes(tmp_path / "ray/eval/highway" / policy)
        assert [r["mean_speed_mps"] for r in remote] == [r["mean_speed_mps"] for r in local]
