"""Evaluation runner, grids, policies and the eval CLI, on the real backends."""

from __future__ import annotations

import csv
import gzip
import json
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import torch

from diacc.cli import main
from diacc.config import ConfigError, ModelConfig, TrainConfig
from diacc.envs.actions import ACTION_NAMES
from diacc.envs.env import BottleneckEnv
from diacc.envs.episode import EpisodeDriver
from diacc.experiments.evaluate import (
    EPISODES_FILE,
    SPEEDS_FILE,
    EvaluationError,
    evaluate,
    load_episodes,
    read_csv,
)
from diacc.experiments.grid import SEED_STREAMS, Cell, GridError, load_grid
from diacc.experiments.policies import EvalSettings, PolicySpec, build_policy, parse_policy
from diacc.learn.checkpoint import save_checkpoint
from diacc.learn.collapse import collapse_warning
from diacc.learn.mappo import make_agent
from diacc.sim.maps import SEGMENT_KINDS

SMALL = Cell("train-50", 10, 0.4, "D1")
#: Seed of SMALL's episode 0 before seed streams (the legacy stream keeps it).
LEGACY_SEED_SMALL_0 = 1259447561
GRID_TOML = """
[[cells]]
map = "train-50"
n_vehicles = 10
cav_penetration = 0.4
style_mix = "D1"
"""
TINY_MODEL = ModelConfig(hidden_dim=16, gat_heads=2, cross_heads=2, cross_dim=16, gru_hidden=16)


def _checkpoint(path: Path, variant: str = "diacc", favour: str | None = None) -> Path:
    """A real untrained checkpoint; ``favour``: its actor's output bias makes that action
    the argmax everywhere (a collapsed policy)."""
    cfg = TrainConfig(variant=variant, model=TINY_MODEL)
    torch.manual_seed(0)
    agent = make_agent(cfg, torch.device("cpu"))
    if favour is not None:
        with torch.no_grad():
            agent.actor.head.bias[ACTION_NAMES.index(favour)] = 1e4
    path.mkdir(parents=True, exist_ok=True)
    save_checkpoint(path / "checkpoint.pt", agent, cfg, 0, 0)
    return path / "checkpoint.pt"


def _float(text: str) -> float:
    return float(text) if text != "nan" else float("nan")


# ----------------------------------------------------------------------------- grids
def test_named_grids_match_the_paper():
    train = load_grid("train")
    assert [(c.map, c.n_vehicles, c.cav_penetration, c.style_mix) for c in train] == [
        ("train-25", 25, 0.4, "D1"),
        ("train-50", 25, 0.4, "D1"),
    ]
    # the paper's five zero-shot rows (its Tables III and IV), on each test map
    rows = [(25, 0.4, "D2"), (25, 0.4, "D3"), (20, 0.4, "D1"), (30, 0.3, "D1"), (40, 0.2, "D1")]
    zero = load_grid("zero-shot")
    assert [(c.map, c.n_vehicles, c.cav_penetration, c.style_mix) for c in zero] == [
        (m, *row) for m in ("test-25", "test-50") for row in rows
    ]
    product = load_grid("zero-shot-product")
    assert len(product) == 2 * 4 * 2 * 2
    assert {c.map for c in product} == {"test-25", "test-50"}
    assert {c.n_vehicles for c in product} == {20, 25, 30, 40}
    assert {c.cav_penetration for c in product} == {0.2, 0.3}
    assert {c.style_mix for c in product} == {"D2", "D3"}
    assert not set(zero) & set(product)  # why the product grid is not the paper's


def test_grid_file_and_seeds(tmp_path):
    path = tmp_path / "grid.toml"
    path.write_text(GRID_TOML + '\n[product]\nmap = ["test-25"]\nn_vehicles = [20, 30]\n')
    cells = load_grid(path)
    assert cells[0] == SMALL and [c.n_vehicles for c in cells[1:]] == [20, 30]
    for stream in SEED_STREAMS:
        seeds = {c.seed(e, stream) for c in cells for e in range(20)}
        assert len(seeds) == 3 * 20 and max(seeds) < 2**31  # distinct, fit SUMO's --seed
    assert SMALL.seed(3, "test") == Cell("train-50", 10, 0.4, "D1").seed(3, "test")  # fixed
    # the legacy stream is the derivation of every result committed before streams
    assert SMALL.seed(0, "legacy") == LEGACY_SEED_SMALL_0


def test_validation_and_test_streams_are_disjoint():
    """Disjoint by construction (parity), whatever the cell or episode."""
    cells = [SMALL, Cell("test-25", 30, 0.3, "D2"), Cell("train-50", 25, 0.4, "D1")]
    validation = {c.seed(e, "validation") for c in cells for e in range(200)}
    test = {c.seed(e, "test") for c in cells for e in range(200)}
    assert all(s % 2 == 0 for s in validation) and all(s % 2 == 1 for s in test)
    assert len(validation) == len(test) == 600 and not validation & test


def test_unknown_stream_is_one_line():
    with pytest.raises(GridError, match="unknown seed stream 'tset'; use test, validation"):
        SMALL.seed(0, "tset")
    with pytest.raises(ConfigError, match="'stream' must be one of test, validation, legacy"):
        EvalSettings(stream="tset")


@pytest.mark.parametrize(
    "text, message",
    [
        (GRID_TOML + "speed = 3\n", "unknown grid cell key 'speed'"),
        ("[[cells]]\nmap = 'train-50'\n", "missing key"),
        (GRID_TOML.replace('"D1"', '"D9"'), "unknown style mix"),
        (GRID_TOML.replace('"train-50"', '"nowhere"'), "unknown map"),
    ],
)
def test_bad_grid_files(tmp_path, text, message):
    path = tmp_path / "grid.toml"
    path.write_text(text)
    with pytest.raises(GridError, match=message):
        load_grid(path)


# ----------------------------------------------------------------------------- runner
@pytest.fixture(scope="module")
def hdv_results(tmp_path_factory):
    out = tmp_path_factory.mktemp("hdv")
    summary = evaluate(
        PolicySpec("pure-hdv"),
        [SMALL],
        2,
        out,
        EvalSettings("highway", episode_steps=40),
        progress=False,
    )
    assert summary.cells_run == [SMALL]
    return out


def test_metrics_equal_recomputation_from_speed_samples(hdv_results):
    episodes = read_csv(hdv_results / EPISODES_FILE)
    samples = read_csv(hdv_results / SPEEDS_FILE)
    assert len(episodes) == 2 and {r["policy"] for r in episodes} == {"pure-hdv"}
    by_episode = defaultdict(list)
    for s in samples:
        by_episode[int(s["episode"])].append(s)
    for row in episodes:
        rows = by_episode[int(row["episode"])]
        speed = np.array([float(s["speed_mps"]) for s in rows])
        kind = np.array([s["segment_kind"] for s in rows])
        vehicle = np.array([int(s["vehicle"]) for s in rows])
        assert row["n_cavs"] == "0" and not any(s["is_cav"] == "True" for s in rows)
        assert int(row["n_speed_samples"]) == speed.size
        assert float(row["mean_speed_mps"]) == pytest.approx(speed.mean(), rel=1e-12)
        assert float(row["std_speed_mps"]) == pytest.approx(speed.std(), rel=1e-12)
        assert float(row["mean_hdv_speed_mps"]) == pytest.approx(speed.mean(), rel=1e-12)
        for k in SEGMENT_KINDS:
            expected = speed[kind == k].mean() if (kind == k).any() else float("nan")
            assert _float(row[f"speed_{k}_mps"]) == pytest.approx(expected, rel=1e-12, nan_ok=True)
        waited = np.unique(vehicle[speed < 3.0]).size
        assert float(row["p_we"]) == pytest.approx(waited / np.unique(vehicle).size)
        assert int(row["n_vehicles_seen"]) == np.unique(vehicle).size == SMALL.n_vehicles


def test_results_name_their_seed_stream(hdv_results, tmp_path):
    """episodes.csv and meta.json name the stream; validation plays other traffic, and a
    directory of one stream is refused another."""
    rows = read_csv(hdv_results / EPISODES_FILE)
    assert [r["stream"] for r in rows] == ["test", "test"]
    assert [int(r["seed"]) for r in rows] == [SMALL.seed(e, "test") for e in range(2)]
    assert json.loads((hdv_results / "meta.json").read_text())["settings"]["stream"] == "test"
    settings = EvalSettings("highway", episode_steps=40, stream="validation")
    evaluate(PolicySpec("pure-hdv"), [SMALL], 2, tmp_path, settings, progress=False)
    rows = read_csv(tmp_path / EPISODES_FILE)
    assert [r["stream"] for r in rows] == ["validation", "validation"]
    assert [int(r["seed"]) for r in rows] == [SMALL.seed(e, "validation") for e in range(2)]
    with pytest.raises(
        EvaluationError, match=r"other 'settings' \(stream: validation, asked test\)"
    ):
        evaluate(
            PolicySpec("pure-hdv"),
            [SMALL],
            2,
            tmp_path,
            EvalSettings("highway", episode_steps=40),
            progress=False,
        )


def test_rerun_skips_finished_cells(hdv_results):
    before = (hdv_results / EPISODES_FILE).read_bytes()
    summary = evaluate(
        PolicySpec("pure-hdv"),
        [SMALL],
        2,
        hdv_results,
        EvalSettings("highway", episode_steps=40),
        progress=False,
    )
    assert summary.cells_run == [] and summary.cells_skipped == [SMALL]
    assert (hdv_results / EPISODES_FILE).read_bytes() == before


def test_merged_results_without_cell_files_are_kept_and_not_rerun(hdv_results, tmp_path):
    """Committed results keep only the merged files: a run over them skips their cells and
    keeps their rows when it adds a cell (it used to rebuild episodes.csv from cells/ alone)."""
    import shutil

    out = tmp_path / "merged-only"
    shutil.copytree(hdv_results, out)
    shutil.rmtree(out / "cells")
    (out / SPEEDS_FILE).unlink()
    before = (out / EPISODES_FILE).read_text()
    other = Cell("train-50", 12, 0.4, "D1")
    settings = EvalSettings("highway", episode_steps=40)
    summary = evaluate(PolicySpec("pure-hdv"), [SMALL, other], 2, out, settings, progress=False)
    assert summary.cells_run == [other] and summary.cells_skipped == [SMALL]
    rows = list(csv.DictReader(open(out / EPISODES_FILE)))
    assert sorted((int(r["n_vehicles"]), int(r["episode"])) for r in rows) == [
        (10, 0),
        (10, 1),
        (12, 0),
        (12, 1),
    ]
    assert (out / EPISODES_FILE).read_text().startswith(before)  # the kept rows, unchanged
    after = (out / EPISODES_FILE).read_bytes()
    again = evaluate(PolicySpec("pure-hdv"), [SMALL, other], 2, out, settings, progress=False)
    assert again.cells_run == [] and (out / EPISODES_FILE).read_bytes() == after  # and stay


def test_worker_processes_give_identical_results(hdv_results, tmp_path):
    evaluate(
        PolicySpec("pure-hdv"),
        [SMALL],
        2,
        tmp_path,
        EvalSettings("highway", episode_steps=40),
        workers=2,
        progress=False,
    )
    assert (tmp_path / EPISODES_FILE).read_bytes() == (hdv_results / EPISODES_FILE).read_bytes()
    assert gzip.decompress((tmp_path / SPEEDS_FILE).read_bytes()) == gzip.decompress(
        (hdv_results / SPEEDS_FILE).read_bytes()
    )


@pytest.mark.parametrize("backend", ["highway", "sumo"])
@pytest.mark.parametrize("policy", ["pure-hdv", "cooperative"])
def test_baselines_run_on_both_backends(tmp_path, backend, policy):
    evaluate(
        PolicySpec(policy),
        [SMALL],
        1,
        tmp_path,
        EvalSettings(backend, episode_steps=15),
        progress=False,
    )
    (row,) = read_csv(tmp_path / EPISODES_FILE)
    assert row["backend"] == backend and row["policy"] == policy
    assert int(row["n_cavs"]) == (0 if policy == "pure-hdv" else 4)
    assert row["sumo_version"].startswith("SUMO 1.") == (backend == "sumo")
    assert 0 < float(row["mean_speed_mps"]) <= 25.0 + 1e-6
    assert 1 <= int(row["steps"]) <= 15


def test_checkpoint_policy_greedy_and_deterministic(tmp_path):
    ckpt = _checkpoint(tmp_path / "run")
    outs = []
    for name in ("a", "b"):
        evaluate(
            PolicySpec(str(ckpt)),
            [SMALL],
            1,
            tmp_path / name,
            EvalSettings("highway", episode_steps=10),
            progress=False,
        )
        outs.append((tmp_path / name / EPISODES_FILE).read_bytes())
    assert outs[0] == outs[1]
    (row,) = read_csv(tmp_path / "a" / EPISODES_FILE)
    assert row["policy"] == "diacc" and row["psar"] == "True" and int(row["psar_decisions"]) > 0


def test_the_driver_counts_the_policy_actions_for_living_cavs():
    """``picked`` holds the policy's choice (before PSAR) for every living CAV and step."""
    policy = build_policy(parse_policy("accelerate"))
    settings = EvalSettings("highway", episode_steps=15)
    driver = EpisodeDriver(policy, policy.env_config(SMALL, settings))
    driver.reset(SMALL.seed(0, "test"))
    living = 0
    while not driver.done:
        living += int(driver._obs.alive.sum())
        driver.step()
    driver.close()
    accelerate = ACTION_NAMES.index("accelerate")
    assert driver.picked[accelerate] == driver.picked.sum() == living > 0


def test_a_collapsed_checkpoint_is_named_in_a_warning(tmp_path, caplog):
    settings = EvalSettings("highway", episode_steps=80)
    for name, ckpt in (
        ("collapsed", _checkpoint(tmp_path / "c", favour="accelerate")),
        ("untouched", _checkpoint(tmp_path / "u")),
        ("scripted", None),  # one action by design: no warning
    ):
        caplog.clear()
        spec = PolicySpec(str(ckpt) if ckpt else "accelerate")
        evaluate(spec, [SMALL], 1, tmp_path / name, settings, progress=False)
        logged = (tmp_path / name / "eval.log").read_text() if name == "collapsed" else ""
        warned = [r.getMessage() for r in caplog.records if "collapsed policy" in r.getMessage()]
        if name == "collapsed":
            assert (
                len(warned) == 1
                and "picked 'accelerate' on 100.0%" in warned[0]
                and "c/checkpoint.pt" in warned[0]
            )
            assert "collapsed policy" in logged
        else:
            assert warned == []


@pytest.mark.parametrize(
    ("counts", "warned"),
    [
        ([0, 0, 300, 0, 0], True),
        ([1, 0, 298, 1, 0], True),  # 99.3 %
        ([2, 0, 296, 2, 0], False),  # 98.7 %
        ([0, 0, 150, 0, 0], False),  # too few decisions to tell
        ([60, 60, 60, 60, 60], False),
    ],
)
def test_collapse_warning_thresholds(counts, warned):
    assert (collapse_warning("diacc", np.array(counts)) is not None) == warned


def test_results_of_the_old_default_horizon_get_no_episodes_of_the_new_one(tmp_path):
    """PSAR's default horizon became "headway" and its full_brake "threat" (2026-12-02),
    then "known" (later that day).
    A results directory written before, whose meta.json names neither, holds "stopping"
    / "bound" episodes of a rule-based policy: continuing it unasked would mix PSARs. A
    checkpoint kept its own."""
    meta = {"policy": "heuristic", "backend": "highway", "settings": {"episode_steps": 10}}
    meta["settings"]["style_preset"] = None
    old = tmp_path / "heuristic"
    old.mkdir()
    (old / "meta.json").write_text(json.dumps(meta))
    run = lambda spec, out, **kw: evaluate(  # noqa: E731
        spec, [SMALL], 1, out, EvalSettings("highway", episode_steps=10, **kw), progress=False
    )
    with pytest.raises(EvaluationError, match="other 'settings'"):
        run(PolicySpec("heuristic"), old)
    with pytest.raises(EvaluationError, match="other 'settings'"):
        run(PolicySpec("heuristic"), old, psar_horizon="stopping", stream="legacy")
    with pytest.raises(EvaluationError, match="other 'settings'"):  # it ran on legacy seeds
        run(PolicySpec("heuristic"), old, psar_horizon="stopping", psar_full_brake="bound")
    with pytest.raises(EvaluationError, match="other 'settings'"):  # it ended at collisions
        run(
            PolicySpec("heuristic"),
            old,
            psar_horizon="stopping",
            psar_full_brake="bound",
            stream="legacy",
        )
    run(
        PolicySpec("heuristic"),
        old,
        psar_horizon="stopping",
        psar_full_brake="bound",
        stream="legacy",
        on_collision="end",
    )
    settings = json.loads((old / "meta.json").read_text())["settings"]
    assert (settings["psar_horizon"], settings["psar_full_brake"]) == ("stopping", "bound")
    ckpt = _checkpoint(tmp_path / "run")  # trained (here: made) with today's default
    old_ckpt = tmp_path / "checkpoint"
    old_ckpt.mkdir()
    meta = {**meta, "policy": "diacc", "checkpoint": str(ckpt.resolve())}
    (old_ckpt / "meta.json").write_text(json.dumps(meta))
    run(PolicySpec(str(ckpt)), old_ckpt, stream="legacy", on_collision="end")
    settings = json.loads((old_ckpt / "meta.json").read_text())["settings"]
    assert (settings["psar_horizon"], settings["psar_full_brake"]) == ("headway", "known")


def test_sampled_actions_are_seeded_and_differ_from_greedy(tmp_path):
    """``--actions sampled``: the same episode seed draws the same actions, and an
    untrained actor's samples are not its argmax."""
    from diacc.experiments.policies import build_policy

    policy = build_policy(PolicySpec(str(_checkpoint(tmp_path / "run")), sampled=True))
    greedy = build_policy(PolicySpec(str(tmp_path / "run" / "checkpoint.pt")))
    assert policy.describe()["actions"] == "sampled" and policy.label == "diacc (sampled)"
    env = BottleneckEnv(policy.env_config(SMALL, EvalSettings("highway")))
    obs, _ = env.reset_arrays(3)
    runs = []
    for _ in range(2):
        policy.begin_episode(env.n_cavs, seed=7)
        runs.append(np.stack([policy.act(obs, t == 0) for t in range(20)]))  # (20, C)
    env.close()
    greedy.begin_episode(env.n_cavs, seed=7)
    argmax = np.stack([greedy.act(obs, t == 0) for t in range(20)])
    np.testing.assert_array_equal(runs[0], runs[1])
    assert (runs[0] != argmax).any() and len(np.unique(runs[0])) > 1


# ----------------------------------------------------------------------------- CLI errors
def _cli_error(capsys, argv: list[str]) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("diacc: error: ") and "\n" not in err
    return err


def test_cli_errors_are_one_line(tmp_path, capsys):
    out = str(tmp_path / "res")
    assert "unknown policy 'greedy'" in _cli_error(
        capsys, ["eval", "--policy", "greedy", "--out", out]
    )
    assert "applies to checkpoints" in _cli_error(
        capsys, ["eval", "--policy", "pure-hdv", "--actions", "sampled", "--out", out]
    )
    ckpt = _checkpoint(tmp_path / "mappo-run", variant="mappo")
    assert "variant 'mappo', not 'diacc'" in _cli_error(
        capsys, ["eval", "--policy", str(ckpt), "--variant", "diacc", "--out", out]
    )
    payload = torch.load(ckpt, weights_only=True)
    payload["obs_spec"]["n_neighbours"] = 4
    torch.save(payload, tmp_path / "other.pt")
    assert "another observation layout" in _cli_error(
        capsys, ["eval", "--policy", str(tmp_path / "other.pt"), "--out", out]
    )
    grid = tmp_path / "grid.toml"
    grid.write_text(GRID_TOML + "lanes = 3\n")
    assert "unknown grid cell key 'lanes'" in _cli_error(
        capsys, ["eval", "--policy", "pure-hdv", "--grid", str(grid), "--out", out]
    )
    (tmp_path / "empty").mkdir()
    assert "holds no evaluation results" in _cli_error(capsys, ["table", str(tmp_path / "empty")])
    assert "holds no evaluation results" in _cli_error(
        capsys, ["plot", "speeds", str(tmp_path / "empty"), "--out", str(tmp_path / "f")]
    )


def test_cli_eval_writes_results(tmp_path, capsys):
    grid = tmp_path / "grid.toml"
    grid.write_text(GRID_TOML)
    out = tmp_path / "res"
    argv = [
        "eval",
        "--policy",
        "pure-hdv",
        "--grid",
        str(grid),
        "--episodes",
        "1",
        "--episode-steps",
        "5",
        "--out",
        str(out),
        "--no-progress",
    ]
    assert main(argv) == 0
    assert "1 cells run, 0 already done" in capsys.readouterr().out
    assert main(argv) == 0
    assert "0 cells run, 1 already done" in capsys.readouterr().out
    with open(out / EPISODES_FILE, newline="") as fh:
        assert len(list(csv.DictReader(fh))) == 1


# -------------------------------------------------------------- highway cooperative CAVs
def test_highway_cooperative_cavs_drive_themselves():
    from diacc.config import SimConfig
    from diacc.sim.backends.base import CavCommands
    from diacc.sim.backends.highway.backend import HighwayBackend
    from diacc.sim.maps import load_map

    road, sim = load_map("train-50"), SimConfig()
    scenario = SMALL.scenario()
    coop = [HighwayBackend(road, SimConfig(cav_mode="cooperative")) for _ in range(2)]
    commanded = HighwayBackend(road, sim)
    states = [b.reset(scenario, 7).env(0) for b in (*coop, commanded)]
    cav = states[0].is_cav
    assert cav.sum() == scenario.n_cavs and np.array_equal(states[2].is_cav, cav)
    rng = np.random.default_rng(0)
    for _ in range(8):
        idle = CavCommands.idle(cav.size)
        noisy = CavCommands(
            rng.integers(-1, 2, cav.size).astype(np.int8)[None], rng.normal(0, 2, cav.size)[None]
        )
        states = [
            coop[0].step(idle).env(0),
            coop[1].step(noisy).env(0),
            commanded.step(idle).env(0),
        ]
    assert np.array_equal(states[0].x_m, states[1].x_m)  # cooperative CAVs ignore commands
    assert np.array_equal(states[0].is_cav, cav)  # and are still reported as CAVs
    # Commanded CAVs hold their speed when idle; cooperative ones accelerate on their own.
    assert np.allclose(states[2].speed_mps[cav], scenario.insert_speed_mps)
    assert states[0].speed_mps[cav].mean() > scenario.insert_speed_mps + 1.0
    with pytest.raises(ConfigError, match="cav_mode"):
        SimConfig(cav_mode="platoon")


def test_results_of_a_demand_cell_load(tmp_path):
    """A demand cell's N follows from its inflow: reading its results back once checked
    N alone against the map (300 vehicles do not fit at t = 0) and failed."""
    from diacc.experiments.grid import make_cell
    from diacc.experiments.report import build_table

    cell = make_cell(
        {"map": "train-50", "cav_penetration": 0.4, "style_mix": "D1", "inflow_vph": 3600.0}
    )
    settings = EvalSettings("highway", episode_steps=3)
    evaluate(PolicySpec("same-mix"), [cell], 1, tmp_path, settings, progress=False)
    _, rows = load_episodes(tmp_path)
    assert float(rows[0]["inflow_vph"]) == 3600.0 and int(rows[0]["n_vehicles"]) > 100
    assert build_table([tmp_path], rows=("speed",)).cells == [cell]
