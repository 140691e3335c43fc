"""``diacc train``: its options and handler (registered by :mod:`diacc.cli.parser`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from diacc.cli import options
from diacc.cli.options import add_command, add_device_arg, add_out_arg, positive_int
from diacc.config import (
    BACKENDS,
    STYLE_PRESETS,
    VARIANTS,
    ConfigError,
    EnvConfig,
    SimConfig,
    TrainConfig,
    build_train_config,
    resolve_road,
    validate,
)
from diacc.sim.scenario import EVERY_CAV


def add_parsers(sub) -> None:
    p = add_command(
        sub,
        "train",
        "train a MAPPO variant (writes a run directory)",
        "Prints the resolved configuration, then trains; the run directory gets\n"
        "config.json, checkpoint.pt, progress.jsonl and TensorBoard logs (tb/).\n"
        "Precedence: defaults < --config file < named options < --set.",
    )
    # Named options default to None ("not given"), so that a --config file's value
    # stands unless the option is given; the help shows the value used then.
    p.add_argument(
        "--variant",
        choices=VARIANTS,
        default=None,
        help="mappo: plain MLP actor; mappo-iadm: + interaction-aware actor; "
        "diacc-nopsar: + C-IEC critic; diacc: + PSAR safety filter "
        f"(default: {TrainConfig.variant})",
    )
    p.add_argument(
        "--backend",
        choices=BACKENDS,
        default=None,
        help=f"simulator to train on (default: {EnvConfig.backend})",
    )
    p.add_argument(
        "--map",
        default=None,
        help=f"shipped map, generated one (gen-test-7) or .toml path (default: {EnvConfig.map})",
    )
    p.add_argument(
        "--steps",
        type=int,
        default=None,
        help="environment steps in total (decisions x environments) "
        f"(default: {TrainConfig.total_steps})",
    )
    p.add_argument(
        "--envs",
        type=int,
        default=None,
        help=f"environments stepped in parallel (default: {TrainConfig.n_envs})",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=None,
        help=f"run seed (networks and traffic) (default: {TrainConfig.seed})",
    )
    add_device_arg(p)
    p.add_argument(
        "--style-preset",
        choices=tuple(STYLE_PRESETS),
        default=None,
        help=f"HDV driving-style parameters, env.sim.style_preset (default: "
        f"{SimConfig.style_preset})",
    )
    add_out_arg(
        p,
        "--run-dir",
        dest="run_dir",
        metavar="DIR",
        default=None,
        help="run directory (default: runs/<variant>-<backend>-<map>-s<seed>)",
    )
    p.add_argument(
        "--config",
        type=Path,
        help="TOML file of config overrides (dotted or nested keys; none by default), e.g. "
        "configs/paper-learner.toml: the paper's network sizes (128, 1 minibatch) instead "
        "of the default learner's (64, 4 minibatches)",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override any config field, e.g. --set env.reward.w_ego=0.8 (repeatable)",
    )
    p.add_argument(
        "--agent-slots",
        type=options.slots_type(EVERY_CAV),
        default=None,
        metavar="{every,N}",
        help="agent slots of a demand scenario, env.scenario.cav_slots: every CAV of the "
        "episode one (default: every CAV an agent) or a cap N on the CAVs the policy drives "
        "at once (CAVs beyond it drive themselves)",
    )
    p.add_argument(
        "--init-from",
        metavar="CHECKPOINT",
        default=None,
        help="start from this checkpoint's networks, with a fresh optimiser and schedules "
        "(fine-tuning, e.g. a highway-trained agent on --backend sumo)",
    )
    p.add_argument(
        "--stop-at",
        type=positive_int,
        default=None,
        metavar="STEPS",
        help="stop with a checkpoint once this many env steps of the --steps schedule are "
        "done (tau and lr follow --steps); --resume goes on",
    )
    p.add_argument("--resume", action="store_true", help="continue from <out>/checkpoint.pt")
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the run that <out> holds (without it, such a directory is refused)",
    )
    p.add_argument(
        "--allow-config-change",
        action="store_true",
        help="with --resume: accept settings other than --steps that differ from the checkpoint's",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def cmd_train(args: argparse.Namespace) -> None:
    from diacc.console import print_config
    from diacc.learn.mappo import check_config, train

    cfg = build_train_config(
        args.config,
        variant=args.variant,
        backend=args.backend,
        map=args.map,
        steps=args.steps,
        envs=args.envs,
        seed=args.seed,
        device=args.device,
        run_dir=args.run_dir,
        style_preset=args.style_preset,
        init_from=args.init_from,
        agent_slots=args.agent_slots,
        sets=args.set,
    )
    resolve_road(cfg.env)  # fail fast on a bad map name
    validate(cfg)  # before the config is printed (train() checks it again)
    if args.resume and args.overwrite:
        raise ConfigError("--resume continues the run that --overwrite would replace: choose one")
    check_config(cfg)  # a config that cannot run is one line, not a table and a line
    print_config(cfg, "diacc train: resolved config", f"full config: {cfg.run_dir}/config.json")
    run_dir = train(
        cfg,
        resume=args.resume,
        progress=not args.no_progress,
        allow_config_change=args.allow_config_change,
        overwrite=args.overwrite,
        stop_at_step=args.stop_at,
    )
    print(f"run directory: {run_dir}  (checkpoint: {run_dir / 'checkpoint.pt'})")


COMMANDS = {"train": cmd_train}
