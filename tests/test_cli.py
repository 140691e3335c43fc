"""`diacc train | simulate | bench` from the command line: one-line errors, small real runs."""

from __future__ import annotations

import json

import pytest

from diacc.cli import main


def _error(capsys, argv: list[str]) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("diacc: error: ") and "\n" not in err, err
    return err


def test_train_rejects_bad_input(tmp_path, capsys):
    run = ["--run-dir", str(tmp_path / "r"), "--no-progress"]
    assert "unknown map 'nowhere'" in _error(capsys, ["train", "--map", "nowhere", *run])
    assert "unknown config key 'reward.nope'" in _error(
        capsys, ["train", "--set", "reward.nope=1", *run]
    )
    assert "expects KEY=VALUE" in _error(capsys, ["train", "--set", "lr", *run])
    assert "does not exist" in _error(capsys, ["train", "--resume", *run])
    bad = tmp_path / "bad.toml"
    bad.write_text("lr = [")
    assert "not valid TOML" in _error(capsys, ["train", "--config", str(bad), *run])
    too_many = tmp_path / "many.toml"
    too_many.write_text("[scenario]\nn_vehicles = 41\n")
    assert "41" in _error(capsys, ["train", "--config", str(too_many), "--steps", "10", *run])


def test_bench_needs_a_target(capsys):
    assert "choose what to benchmark" in _error(capsys, ["bench"])


def test_train_writes_a_run_directory(tmp_path, capsys):
    config = tmp_path / "small.toml"
    config.write_text(
        "rollout_steps = 10\nepochs = 1\n[scenario]\nn_vehicles = 8\n"
        "cav_penetration = 0.25\n[model]\nhidden_dim = 32\ngru_hidden = 32\n"
        "cross_dim = 32\n"
    )
    run = tmp_path / "run"
    assert (
        main(
            [
                "train",
                "--steps",
                "20",
                "--envs",
                "2",
                "--config",
                str(config),
                "--run-dir",
                str(run),
                "--no-progress",
            ]
        )
        == 0
    )
    assert (run / "checkpoint.pt").exists() and any((run / "tb").iterdir())
    record = json.loads((run / "progress.jsonl").read_text().splitlines()[-1])
    assert record["global_step"] == 20
    assert {
        "approx_kl",
        "clipfrac",
        "explained_variance",
        "env_steps_per_s",
        "psar/force_brake",
        "reward/individual",
    } <= set(record)
    stored = json.loads((run / "config.json").read_text())
    assert stored["scenario"]["n_vehicles"] == 8 and stored["model"]["hidden_dim"] == 32


@pytest.mark.parametrize("backend", ["highway", "sumo"])
def test_simulate_prints_metrics(backend, capsys):
    assert main(["simulate", "--backend", backend, "--map", "train-50", "--steps", "20"]) == 0
    out = capsys.readouterr().out
    assert "mean_speed_mps" in out and "p_we" in out
