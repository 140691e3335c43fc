"""`diacc sweep` on the default (no Ray) engine: runs, skips finished runs, one-line errors."""

from __future__ import annotations

import pytest

from diacc.cli import main

SMALL = [
    "--set", "rollout_steps=10", "--set", "minibatches=1", "--set", "epochs=1",
    "--set", "env.scenario.n_vehicles=8",
    "--set", "env.scenario.cav_penetration=0.25", "--set", "env.sim.episode_steps=10",
    "--set", "model.hidden_dim=16", "--set", "model.gru_hidden=16", "--set", "model.cross_dim=16",
]  # fmt: skip


def test_local_sweep_trains_then_skips(tmp_path, capsys):
    argv = ["sweep", "--variants", "mappo", "--seeds", "1,2", "--steps", "10", "--envs", "1"]
    argv += ["--out", str(tmp_path), *SMALL]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "2 runs (1 variants x 1 maps x 2 seeds) on engine local" in out
    assert "[2/2] trained mappo train-25 seed 2" in out and "nan" not in out
    for seed in (1, 2):
        assert (tmp_path / f"mappo-highway-train-25-s{seed}" / "checkpoint.pt").exists()
    assert main(argv) == 0
    assert capsys.readouterr().out.count("skipped mappo") == 2


def test_tau_sweep_keeps_each_setting_apart(tmp_path, capsys):
    """Two tau_final values at a tiny budget: a run dir, a config and a curve each; a rerun
    skips them; the same dirs with another setting are refused, not skipped."""
    import json

    from diacc.experiments.plots import group_curves

    argv = ["sweep", "--variants", "diacc", "--seeds", "1", "--steps", "200", "--envs", "1"]
    # --out-dir: the old name of --out, still accepted
    argv += ["--out-dir", str(tmp_path), "--sweep", "env.reward.tau_final=0.05,0.5", *SMALL]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "2 runs (1 variants x 1 maps x 2 settings x 1 seeds)" in out
    runs = [tmp_path / f"diacc-highway-train-25-s1-tau_final{v}" for v in ("0.05", "0.5")]
    for run, tau in zip(runs, (0.05, 0.5), strict=True):
        config = json.loads((run / "config.json").read_text())
        assert config["env"]["reward"]["tau_final"] == tau
        progress = (run / "progress.jsonl").read_text().splitlines()
        assert json.loads(progress[-1])["global_step"] == 200
        assert json.loads(progress[-1])["reward/tau"] == pytest.approx(tau)  # annealed by then
    assert (tmp_path / "curves-train-25.png").stat().st_size > 1000
    assert set(group_curves(runs, ("reward/individual",))) == {
        "diacc (highway) tau_final=0.05",
        "diacc (highway) tau_final=0.5",
    }
    assert main(argv) == 0
    assert capsys.readouterr().out.count("skipped diacc train-25 tau_final=") == 2
    assert main([*argv, "--set", "lr=0.001"]) == 2
    assert "was trained with another lr" in capsys.readouterr().err


def test_sweep_rejects_bad_input(tmp_path, capsys):
    for extra, message in (
        (["--variants", "diacc,nope"], "unknown variant 'nope'"),
        (["--seeds", "1,x"], "comma-separated list of int"),
        (["--maps", "nowhere"], "unknown map 'nowhere'"),
        (["--ray-address", "auto"], "--ray-address / --ray-cpus need --engine ray"),
        (["--sweep", "env.reward.nope=1"], "--sweep: unknown config key 'env.reward.nope'"),
        (["--sweep", "env.reward.tau_final="], "the value list is empty"),
        (["--sweep", "env.reward.tau_final"], "--sweep expects KEY=V1,V2"),
        (["--sweep", "env.reward.tau_final=0.1,x"], "expects float, got 'x'"),
        (["--sweep", "env.reward.tau_final=0"], "must be > 0, got 0.0"),
        (["--sweep", "env.reward.w_ego=-0.5"], "must be >= 0, got -0.5"),
        (["--sweep", "env.reward.tau_final=0.1,0.10"], "two settings the same value"),
        (["--sweep", "env.reward.w_ego,env.reward.w_global=0.5:0.5,1"], "needs 2 part(s)"),
        (["--sweep", "seed=1,2"], "use --seeds"),
        (["--study", "lambda"], "unknown study 'lambda'; use one of tau, w_e"),
    ):
        out = tmp_path / "out"
        assert main(["sweep", "--out-dir", str(out), *extra]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("diacc: error: ") and message in err and "\n" not in err, err
        assert not out.exists()


def test_studies_are_the_papers():
    """tau: annealed 2 -> 0.05 against fixed 0.05, 2, 10; w_e: w_g = 1 - w_e throughout."""
    from diacc.config import TrainConfig
    from diacc.experiments.sweepaxes import STUDIES, sweep_settings

    tau = [s.changes for s in sweep_settings(TrainConfig(), [STUDIES["tau"]])]
    assert [(c["env.reward.tau_init"], c["env.reward.tau_final"]) for c in tau] == [
        (2.0, 0.05),
        (0.05, 0.05),
        (2.0, 2.0),
        (10.0, 10.0),
    ]
    w_e = [s.changes for s in sweep_settings(TrainConfig(), [STUDIES["w_e"]])]
    assert [c["env.reward.w_ego"] for c in w_e] == [0.0, 0.2, 0.4, 0.6, 0.8, 1.0]
    assert all(c["env.reward.w_global"] == pytest.approx(1 - c["env.reward.w_ego"]) for c in w_e)


def test_ray_engine_without_ray_says_how_to_install(tmp_path, monkeypatch, capsys):
    import sys

    monkeypatch.setitem(sys.modules, "ray", None)  # as if Ray were not installed
    argv = ["sweep", "--variants", "mappo", "--seeds", "1", "--steps", "10", "--envs", "1"]
    assert main([*argv, "--out-dir", str(tmp_path), "--engine", "ray", *SMALL]) == 2
    assert capsys.readouterr().err.strip() == (
        'diacc: error: Ray is not installed: pip install -e ".[ray]" (or use --engine local)'
    )
