"""`diacc sweep` on the default (no Ray) engine: runs, skips finished runs, one-line errors."""

from __future__ import annotations

from diacc.cli import main

SMALL = [
    "--set", "rollout_steps=10", "--set", "epochs=1", "--set", "env.scenario.n_vehicles=8",
    "--set", "env.scenario.cav_penetration=0.25", "--set", "env.sim.episode_steps=10",
    "--set", "model.hidden_dim=16", "--set", "model.gru_hidden=16", "--set", "model.cross_dim=16",
]  # fmt: skip


def test_local_sweep_trains_then_skips(tmp_path, capsys):
    argv = ["sweep", "--variants", "mappo", "--seeds", "1,2", "--steps", "10", "--envs", "1"]
    argv += ["--out-dir", str(tmp_path), *SMALL]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "2 runs (1 variants x 1 maps x 2 seeds) on engine local" in out
    assert "[2/2] trained mappo train-25 seed 2" in out and "nan" not in out
    for seed in (1, 2):
        assert (tmp_path / f"mappo-highway-train-25-s{seed}" / "checkpoint.pt").exists()
    assert main(argv) == 0
    assert capsys.readouterr().out.count("skipped mappo") == 2


def test_sweep_rejects_bad_input(capsys):
    for extra, message in (
        (["--variants", "diacc,nope"], "unknown variant 'nope'"),
        (["--seeds", "1,x"], "comma-separated list of int"),
        (["--maps", "nowhere"], "unknown map 'nowhere'"),
        (["--ray-address", "auto"], "--ray-address / --ray-cpus need --engine ray"),
    ):
        assert main(["sweep", *extra]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("diacc: error: ") and message in err and "\n" not in err


def test_ray_engine_without_ray_says_how_to_install(tmp_path, monkeypatch, capsys):
    import sys

    monkeypatch.setitem(sys.modules, "ray", None)  # as if Ray were not installed
    argv = ["sweep", "--variants", "mappo", "--seeds", "1", "--steps", "10", "--envs", "1"]
    assert main([*argv, "--out-dir", str(tmp_path), "--engine", "ray", *SMALL]) == 2
    assert capsys.readouterr().err.strip() == (
        'diacc: error: Ray is not installed: pip install -e ".[ray]" (or use --engine local)'
    )
