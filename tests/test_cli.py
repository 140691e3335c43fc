"""`diacc train | simulate | bench` from the command line: one-line errors, small real runs."""

from __future__ import annotations

import argparse
import json
import re

import pytest

from diacc import __version__
from diacc.cli import bench as cli_bench
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
    argv = [
        "simulate",
        "--backend",
        backend,
        "--map",
        "train-50",
        "--episode-steps",
        "20",
        "--seed",
        "3",
    ]
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


#: Options renamed so that each name means one thing (issue 24): --steps is the total
#: environment steps of training only. (command, new option, former name, value, dest)
RENAMED = [
    ("simulate", "--episode-steps", "--steps", "7", "episode_steps"),
    ("render", "--episode-steps", "--steps", "7", "episode_steps"),
    ("plot timespace", "--episode-steps", "--steps", "7", "episode_steps"),
    ("train", "--out", "--run-dir", "d", "run_dir"),
    ("sweep", "--out", "--out-dir", "d", "out"),
]


def _parse(command: str, *argv: str) -> argparse.Namespace:
    policy = ["--policy", "pure-hdv"] if command in ("render", "plot timespace") else []
    return build_parser().parse_args([*command.split(), *policy, *argv])


@pytest.mark.parametrize(("command", "new", "old", "value", "dest"), RENAMED)
def test_former_option_names_still_work_and_help_shows_only_the_new(command, new, old, value, dest):
    assert str(getattr(_parse(command, new, value), dest)) == value
    assert str(getattr(_parse(command, old, value), dest)) == value
    parser = dict(_subparsers(build_parser()))[command]
    options = re.findall(r"--[a-z-]+", parser.format_help())
    assert new in options and old not in options


def test_steps_means_environment_steps_of_training_only():
    commands = dict(_subparsers(build_parser()))
    training = {"train", "sweep", "reproduce"}
    for name, sub in commands.items():
        if "--steps" in re.findall(r"--[a-z-]+", sub.format_help()):
            assert name in training, f"diacc {name} --steps"
    for name in training:
        text = " ".join(commands[name].format_help().split())
        assert "--steps STEPS environment steps" in text and "(decisions x environments)" in text


@pytest.mark.parametrize(
    ("argv", "episode_steps", "timing_steps"),
    [
        (["--headway", "--episode-steps", "9"], 9, None),
        (["--headway", "--steps", "9"], 9, None),  # --steps: the former name of both
        (["--headroom", "--steps", "9"], 9, None),
        (["--env-batch", "--timing-steps", "9"], None, 9),
        (["--backend", "sumo", "--steps", "9"], None, 9),
        (["--safety", "--steps", "9"], None, None),  # ignored by --safety, as before
        (["--headway", "--steps", "9", "--episode-steps", "4"], 4, None),  # the new name wins
    ],
)
def test_bench_former_steps_keeps_its_meaning(argv, episode_steps, timing_steps):
    args = _parse("bench", *argv)
    cli_bench.bench_lengths(args)
    assert (args.episode_steps, args.timing_steps) == (episode_steps, timing_steps)


def test_bench_envbatch_timing_steps_and_its_former_name():
    from diacc.experiments.bench import envbatch

    parser = envbatch.build_parser()
    assert parser.parse_args([]).timing_steps == 60
    assert parser.parse_args(["--timing-steps", "5"]).timing_steps == 5
    assert parser.parse_args(["--steps", "5"]).timing_steps == 5
    assert "--steps" not in re.findall(r"--[a-z-]+", parser.format_help())


def test_device_defaults_to_the_training_config_default_everywhere():
    from diacc.config import TrainConfig

    commands = dict(_subparsers(build_parser()))
    with_device = {n for n, sub in commands.items() if "--device" in sub.format_help()}
    assert with_device == {"train", "sweep", "reproduce", "bench"}
    for name in with_device:
        (action,) = [a for a in commands[name]._actions if "--device" in a.option_strings]
        assert action.default is None and action.choices == ("auto", "cpu", "cuda")
        text = " ".join(commands[name].format_help().split())
        assert f"(default: {TrainConfig.device})" in text
    assert cli_bench.bench_device(None) in ("cpu", "cuda")  # what auto means on this machine


def test_simulate_former_steps_runs(capsys):
    assert main(["simulate", "--steps", "3", "--vehicles", "5"]) == 0
    assert "at most 3 steps" in capsys.readouterr().out.splitlines()[0]


def test_runs_saved_with_device_cpu_resume_under_the_auto_default():
    """sweep's and reproduce's --device was cpu before it became auto: their run
    directories continue where auto means cpu, and are refused where it means cuda."""
    import dataclasses
    from pathlib import Path

    import torch

    from diacc.config import TrainConfig
    from diacc.learn.trainer import check_resume_config

    saved = dataclasses.asdict(TrainConfig(device="cpu"))
    changed = check_resume_config(saved, TrainConfig(device="auto"), Path("run"), True)
    assert changed == (["device"] if torch.cuda.is_available() else [])
    assert check_resume_config(saved, TrainConfig(device="cuda"), Path("run"), True) == ["device"]


def test_every_help_text_renders_percent_signs_once():
    """Descriptions are printed as written (raw formatter) while argument help goes through
    %-formatting: a ``%%`` in a description reaches the user as ``%%``."""
    import argparse

    from diacc.cli.parser import build_parser

    parser = build_parser()
    subparsers = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, sub in subparsers.choices.items():
        assert "%%" not in sub.format_help(), name
        for action in sub._actions:
            if isinstance(action, argparse._SubParsersAction):
                for inner_name, inner in action.choices.items():
                    assert "%%" not in inner.format_help(), f"{name} {inner_name}"
