"""`diacc train | simulate | bench` from the command line: one-line errors, small real runs."""

from __future__ import annotations

import argparse
import json
import re

import pytest

from diacc import __version__
from diacc.cli import build_parser, main


def _error(capsys, argv: list[str]) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("diacc: error: ") and "\n" not in err, err
    return err


def test_train_rejects_bad_input(tmp_path, capsys):
    run = ["--out", str(tmp_path / "r"), "--no-progress"]
    assert "unknown map 'nowhere'" in _error(capsys, ["train", "--map", "nowhere", *run])
    assert "unknown config key 'env.reward.nope'" in _error(
        capsys, ["train", "--set", "env.reward.nope=1", *run]
    )
    assert "expects KEY=VALUE" in _error(capsys, ["train", "--set", "lr", *run])
    assert "does not exist" in _error(capsys, ["train", "--resume", *run])
    bad = tmp_path / "bad.toml"
    bad.write_text("lr = [")
    assert "not valid TOML" in _error(capsys, ["train", "--config", str(bad), *run])
    too_many = tmp_path / "many.toml"
    too_many.write_text("[env.scenario]\nn_vehicles = 41\n")
    assert "41" in _error(capsys, ["train", "--config", str(too_many), "--steps", "2000", *run])


def test_only_user_errors_are_one_line(monkeypatch, capsys):
    """A DiaccError is a one-line error; any other exception is a bug and keeps its traceback."""
    from diacc import cli
    from diacc.errors import DiaccError

    def user_mistake(args):
        raise DiaccError("bad input\nsecond line")

    def bug(args):
        raise ValueError("a bug")

    monkeypatch.setitem(cli.COMMANDS, "simulate", user_mistake)
    assert _error(capsys, ["simulate"]) == "diacc: error: bad input"
    monkeypatch.setitem(cli.COMMANDS, "simulate", bug)
    with pytest.raises(ValueError, match="a bug"):
        main(["simulate"])


def test_bench_needs_a_target(capsys):
    assert "choose what to benchmark" in _error(capsys, ["bench"])


def test_train_writes_a_run_directory(tmp_path, capsys):
    config = tmp_path / "small.toml"
    config.write_text(
        # --envs 2 x 10 steps are 2 sequences: minibatches 1 (the default 4 needs 4)
        "rollout_steps = 10\nepochs = 1\nn_envs = 4\nseed = 5\nminibatches = 1\n"
        "[env.scenario]\nn_vehicles = 8\n"
        "cav_penetration = 0.25\n[env.sim]\nepisode_steps = 10\n[model]\nhidden_dim = 32\n"
        "gru_hidden = 32\ncross_dim = 32\n"
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
                "--style-preset",
                "zipper",
                "--run-dir",  # the old name of --out still works
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
    assert stored["env"]["scenario"]["n_vehicles"] == 8 and stored["model"]["hidden_dim"] == 32
    # the file's seed stands (no --seed), --envs beats the file's n_envs
    assert stored["seed"] == 5 and stored["n_envs"] == 2
    assert stored["env"]["sim"]["style_preset"] == "zipper"
    out = capsys.readouterr().out
    assert out.index("resolved config") < out.index("run directory")
    assert re.search(r"total_steps\s+.*20\s+.*3000000", out)  # value and default
    assert re.search(r"env\.scenario\.n_vehicles\s+.*8\s+.*25", out)  # changed nested field
    assert "env.sim.step_s" not in out  # unchanged nested fields: see config.json


@pytest.mark.parametrize("backend", ["highway", "sumo"])
def test_simulate_prints_metrics(backend, capsys):
    argv = ["simulate", "--backend", backend, "--map", "train-50", "--steps", "20", "--seed", "3"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    context = out.splitlines()[0]
    assert f"backend {backend}" in context and "map train-50" in context and "seed 3" in context
    assert "style preset realistic" in context and "(0 CAVs)" in context
    assert "nan" not in out.lower()
    assert "mean CAV speed" not in out and "reduction25" not in out  # not applicable: omitted
    assert re.search(r"mean speed +: \d+\.\d\d ± \d+\.\d\d m/s", out)
    assert re.search(r"p\(WE\) waiting events +: \d+\.\d %", out)


def _subparsers(parser: argparse.ArgumentParser):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield name, sub
                yield from ((f"{name} {n}", p) for n, p in _subparsers(sub))


def test_every_option_is_described_with_its_default():
    parser = build_parser()
    commands = dict(_subparsers(parser))
    assert {"train", "eval", "table", "plot curves", "render", "simulate", "bench"} <= set(commands)
    for name, sub in commands.items():
        assert sub.description, f"diacc {name} has no description"
        text = sub.format_help()
        for action in sub._actions:
            if not action.option_strings or action.help == argparse.SUPPRESS:
                continue
            flag = action.option_strings[-1]
            assert action.help, f"diacc {name} {flag} has no help text"
            if action.default not in (None, False, [], argparse.SUPPRESS) and not action.required:
                assert f"(default: {action.default})" in " ".join(text.split()), (name, flag)


def test_version_and_plain_help(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0 and capsys.readouterr().out.strip() == f"diacc {__version__}"
    text = build_parser().format_help()
    assert "``" not in text and "COMMAND --help" in text
