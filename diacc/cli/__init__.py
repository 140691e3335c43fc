"""Command line: ``diacc train | eval | sweep | reproduce | table | plot | render | scorecard |
simulate | bench | convert-checkpoint``.

This module holds :func:`main` (also ``python -m diacc.cli``) and ``train``, ``bench``,
``simulate``, ``convert-checkpoint``; :mod:`.eval` has ``eval``, ``table``, ``plot``,
``render``, ``scorecard``; :mod:`.scale` ``sweep``; :mod:`.reproduce` ``reproduce``. The
command line sits above every other layer and nothing in ``diacc`` imports it.

Every command turns known failures (bad map, backend, config key, checkpoint,
crashed simulator: a :class:`~diacc.errors.DiaccError`) into a one-line
``diacc: error: ...`` message and exit code 2 (set ``DIACC_DEBUG=1`` to see
the traceback); any other exception is a bug and shows its traceback.
Recoveries are one ``diacc: warning: ...`` line each (:mod:`diacc.runlog`);
an interrupted ``train`` exits with 128 + the signal number after saving a
checkpoint; a closed output pipe (``diacc simulate | head``) ends quietly.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from pathlib import Path

from diacc import __version__
from diacc.cli import eval as cli_eval
from diacc.cli import reproduce as cli_reproduce
from diacc.cli import scale as cli_scale
from diacc.config import (
    BACKENDS,
    HORIZON_MODES,
    STYLE_PRESETS,
    VARIANTS,
    ConfigError,
    EnvConfig,
    SimConfig,
    TrainConfig,
    build_train_config,
    validate,
)
from diacc.errors import DiaccError
from diacc.sim.scenario import SCENARIO_KINDS

DESCRIPTION = """\
diacc: multi-agent reinforcement learning for connected automated vehicles
(CAVs) among human drivers in highway bottlenecks, on highway-env and SUMO.
Run 'diacc COMMAND --help' for a command's options; every option shows its
default."""


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Shows each option's default, except where there is none to show (None, off
    flags: their help says what happens then); keeps descriptions' line breaks."""

    def _get_help_string(self, action: argparse.Action) -> str:
        if action.default is None or action.default is False or action.default == []:
            return action.help or ""
        return super()._get_help_string(action)


class Parser(argparse.ArgumentParser):
    """``diacc``'s parser: its help formatter on every (sub)command."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str):
        """A bad option is one line, like every other error (argparse printed the usage first,
        several lines for the larger commands)."""
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _train_parser(sub) -> None:
    p = cli_scale.add_command(
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
        "--map", default=None, help=f"shipped map name or .toml path (default: {EnvConfig.map})"
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
    cli_scale.add_device_arg(p)
    p.add_argument(
        "--style-preset",
        choices=tuple(STYLE_PRESETS),
        default=None,
        help=f"HDV driving-style parameters, env.sim.style_preset (default: "
        f"{SimConfig.style_preset})",
    )
    cli_scale.add_out_arg(
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
        "--init-from",
        metavar="CHECKPOINT",
        default=None,
        help="start from this checkpoint's networks, with a fresh optimiser and schedules "
        "(fine-tuning, e.g. a highway-trained agent on --backend sumo)",
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
    from diacc.sim.maps import load_map

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
        sets=args.set,
    )
    load_map(cfg.env.map)  # fail fast on a bad map name
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
    )
    print(f"run directory: {run_dir}  (checkpoint: {run_dir / 'checkpoint.pt'})")


def _bench_parser(sub) -> None:
    p = cli_scale.add_command(
        sub,
        "bench",
        "speed benchmarks, measured side by side in one run",
        "Choose at least one of --backend, --models, --training, --env-batch, --safety, "
        "--headway, --headroom, --fidelity.",
    )
    p.add_argument("--backend", choices=BACKENDS, help="backend vs its reference simulator loop")
    p.add_argument("--models", action="store_true", help="network sizes and forward/update times")
    p.add_argument("--training", action="store_true", help="end-to-end training env-steps/s")
    p.add_argument(
        "--env-batch",
        action="store_true",
        help="env stepping per core: E envs on own simulators vs one batched simulator (highway)",
    )
    p.add_argument(
        "--safety",
        action="store_true",
        help="scripted CAVs with and without PSAR on every map (both backends, or --backend)",
    )
    p.add_argument(
        "--headway",
        action="store_true",
        help="CAV time gaps to their leaders under each PSAR horizon (both backends, or --backend)",
    )
    p.add_argument(
        "--headroom",
        action="store_true",
        help="reference delays per training map: free flow, pure HDV, same-mix, heuristic, "
        "cooperative, 100 %% CAVs (highway, or --backend)",
    )
    p.add_argument(
        "--fidelity",
        action="store_true",
        help="pure-HDV outflow of the demand scenario, highway vs SUMO side by side "
        "(train-50; --inflow, --episodes seeds, --style-preset, --demand-s, --warmup-s)",
    )
    p.add_argument(
        "--agent",
        action="append",
        default=[],
        metavar="CHECKPOINT",
        help="a trained agent (checkpoint.pt or run directory) measured by --headroom after "
        "the references, on the same traffic (repeatable)",
    )
    p.add_argument(
        "--references",
        default=None,
        help="comma-separated reference rows of --headroom (default: all): "
        "pure-hdv, same-mix, heuristic, cooperative, cavs-100 (the heuristic with 100 %% CAVs)",
    )
    p.add_argument(
        "--agent-actions",
        nargs="+",
        choices=("greedy", "sampled"),
        default=["greedy"],
        help="actions of each --agent: argmax, sampled (seeded), or both",
    )
    p.add_argument(
        "--scenario",
        choices=SCENARIO_KINDS,
        default="release",
        help="scenario kind of --headroom: the one-shot release (train-25, train-50) or "
        "demand (train-50, needs --inflow)",
    )
    p.add_argument(
        "--inflow",
        type=float,
        nargs="+",
        default=None,
        help="vehicles per hour entering the route in --headroom --scenario demand (one), "
        "or in --fidelity (default 2400 3200 4000 4800)",
    )
    p.add_argument(
        "--demand-s",
        type=float,
        default=None,
        help="seconds of demand of --scenario demand (default 480, as benchmarks/results/demand)",
    )
    p.add_argument(
        "--warmup-s",
        type=float,
        default=None,
        help="seconds of --scenario demand the metrics ignore (default 120)",
    )
    p.add_argument(
        "--horizon",
        choices=HORIZON_MODES,
        default=None,
        help="PSAR horizon of --safety / --headroom (default: PSARConfig's)",
    )
    p.add_argument(
        "--style-preset",
        choices=tuple(STYLE_PRESETS),
        default=None,
        help="style preset of --safety / --headway / --headroom (default: each one's)",
    )
    p.add_argument(
        "--episodes",
        type=int,
        default=None,
        help="seeded episodes per row (--safety 20, --headway and --headroom 4)",
    )
    p.add_argument(
        "--episode-steps",
        type=int,
        default=None,
        help="decision steps per episode of --safety / --headway / --headroom (default: "
        f"--safety {SimConfig.episode_steps}, --headway 330, --headroom the scenario's)",
    )
    p.add_argument(
        "--policies",
        default=None,
        help="comma-separated scripted policies of --safety (default: all, with and without PSAR)",
    )
    p.add_argument(
        "--timing-steps",
        type=int,
        default=None,
        help="steps to time of --backend / --env-batch (default: highway 200, sumo 500, "
        "--env-batch 60 vector steps)",
    )
    cli_scale.add_device_arg(p, "torch device of --models and --training's PPO update")
    # --steps, the former name of both --timing-steps and --headway / --headroom's
    # --episode-steps: hidden, still accepted (cmd_bench gives it the meaning it had)
    p.add_argument("--steps", dest="legacy_steps", type=int, default=None, help=argparse.SUPPRESS)


def bench_device(name: str | None) -> str:
    """The concrete torch device (``cpu``, ``cuda``) of ``--device``, so that the
    benchmark tables name the device they measured, not ``auto``."""
    from diacc.learn.trainer import resolve_device

    return str(resolve_device(name or TrainConfig.device))


def bench_lengths(args: argparse.Namespace) -> None:
    """Check ``bench``'s step counts and give the hidden ``--steps`` the meaning it had
    before it was split: episode steps of --headway / --headroom, else steps to time
    (--safety ignored it); the new names win where both are given."""
    lengths = {
        "--steps": args.legacy_steps,
        "--episode-steps": args.episode_steps,
        "--timing-steps": args.timing_steps,
    }
    for flag, value in lengths.items():
        if value is not None and value < 1:
            raise ConfigError(f"{flag} must be >= 1, got {value}")
    if args.legacy_steps is None or args.safety:
        return
    if args.headway or args.headroom:
        args.episode_steps = args.episode_steps or args.legacy_steps
    else:
        args.timing_steps = args.timing_steps or args.legacy_steps


def cmd_bench(args: argparse.Namespace) -> None:
    ran = False
    if args.episodes is not None and args.episodes < 1:
        raise ConfigError(f"--episodes must be >= 1, got {args.episodes}")
    bench_lengths(args)
    demand_flags = {
        "--inflow": args.inflow,
        "--demand-s": args.demand_s,
        "--warmup-s": args.warmup_s,
    }
    given = [flag for flag, value in demand_flags.items() if value is not None]
    given += ["--scenario demand"] * (args.scenario == "demand")
    if args.fidelity and args.scenario == "release":
        given = []  # --fidelity runs the demand scenario: its flags apply
    if given and not (args.headroom and args.scenario == "demand"):
        raise ConfigError(f"{given[0]} needs --headroom with --scenario demand or --fidelity")
    if (args.agent or args.references) and not args.headroom:
        raise ConfigError(f"{'--agent' if args.agent else '--references'} needs --headroom")
    if args.safety:
        from diacc.experiments.bench import safety

        backends = (args.backend,) if args.backend else BACKENDS
        policies = safety.POLICIES
        if args.policies is not None:
            policies = tuple(p.strip() for p in args.policies.split(",") if p.strip())
            unknown = [p for p in policies if p not in safety.POLICIES]
            if unknown or not policies:
                raise ConfigError(
                    f"unknown --policies entry {(unknown or [''])[0]!r}; use some of "
                    f"{', '.join(safety.POLICIES)}"
                )
        safety.run(
            backends=backends,
            policies=policies,
            episodes=args.episodes or 20,
            style_preset=args.style_preset,
            episode_steps=args.episode_steps,
            horizon=args.horizon,
        )
        return
    if args.headway:
        from diacc.experiments.bench import headway

        headway.run(
            backends=(args.backend,) if args.backend else BACKENDS,
            episodes=args.episodes or 4,
            style_preset=args.style_preset or "paper-congestion",
            **({"steps": args.episode_steps} if args.episode_steps else {}),
        )
        return
    if args.fidelity:
        from diacc.experiments.bench import fidelity

        timing = {"demand_s": args.demand_s, "warmup_s": args.warmup_s}
        preset = {"preset": args.style_preset}
        fidelity.run(
            inflows_vph=tuple(args.inflow or fidelity.INFLOWS_VPH),
            seeds=args.episodes or 1,
            settings=fidelity.FlowSettings(
                **{k: v for k, v in {**timing, **preset}.items() if v is not None}
            ),
            backends=(args.backend,) if args.backend else BACKENDS,
        )
        return
    if args.headroom:
        from diacc.experiments.bench import headroom

        demand = None
        if args.scenario == "demand":
            if args.inflow is None or len(args.inflow) != 1:
                raise ConfigError("--scenario demand needs --inflow (one value, vehicles per hour)")
            timing = {"demand_s": args.demand_s, "warmup_s": args.warmup_s}
            demand = headroom.demand_scenario(
                args.inflow[0], **{k: v for k, v in timing.items() if v is not None}
            )
        headroom.run(
            backends=(args.backend,) if args.backend else ("highway",),
            episodes=args.episodes or 4,
            style_preset=args.style_preset,
            steps=args.episode_steps,
            horizon=args.horizon,
            demand=demand,
            agents=tuple(args.agent),
            agent_actions=tuple(args.agent_actions),
            references=headroom.pick_references(args.references),
        )
        return
    if args.backend == "highway":
        from diacc.experiments.bench import highway

        highway.run(**({"steps": args.timing_steps} if args.timing_steps else {}))
        ran = True
    if args.backend == "sumo":
        from diacc.experiments.bench import sumo

        sumo.run(**({"steps": args.timing_steps} if args.timing_steps else {}))
        ran = True
    if args.models:
        from diacc.experiments.bench import models

        models.run(device=bench_device(args.device))
        ran = True
    if args.training:
        from diacc.experiments.bench import training

        training.run(device=bench_device(args.device))
        ran = True
    if args.env_batch:
        from diacc.experiments.bench import envbatch

        envbatch.run(**({"steps": args.timing_steps} if args.timing_steps else {}))
        ran = True
    if not ran:
        raise ConfigError(
            "choose what to benchmark: --backend highway|sumo, --models, --training, "
            "--env-batch, --safety, --headway or --headroom"
        )


def _simulate_parser(sub) -> None:
    p = cli_scale.add_command(
        sub,
        "simulate",
        "simulate one episode of human-driven traffic and print its metrics",
        "HDVs drive themselves (IDM + MOBIL on highway, IDM + LC2013 on SUMO); CAVs,\n"
        "if --penetration > 0, get no commands and keep their lane and speed. To\n"
        "run a trained policy or the cooperative baseline, use 'diacc eval'.",
    )
    p.add_argument("--backend", choices=BACKENDS, default="highway", help="simulator")
    p.add_argument("--map", default="train-25", help="shipped map name or .toml path")
    p.add_argument("--vehicles", type=int, default=25, help="vehicles inserted at t = 0 (N)")
    p.add_argument(
        "--penetration", type=float, default=0.0, help="CAV share rho (CAVs keep lane and speed)"
    )
    p.add_argument("--mix", default="D1", help="HDV style mix: D1, D2 or D3 (paper Table I)")
    p.add_argument(
        "--style-preset",
        choices=tuple(STYLE_PRESETS),
        default="realistic",
        help="HDV driving-style parameters (paper: authors' values)",
    )
    cli_scale.add_renamed_arg(
        p,
        "--episode-steps",
        "--steps",  # its former name
        dest="episode_steps",
        type=int,
        default=150,
        help="decision steps (1 s) at most",
    )
    p.add_argument("--seed", type=cli_scale.seed_type, default=0, help="traffic seed")


def cmd_simulate(args: argparse.Namespace) -> None:
    from diacc.config import ObservationConfig
    from diacc.console import metric_lines, print_lines
    from diacc.envs.episode import EpisodeDriver, play_episode
    from diacc.experiments.policies import Policy
    from diacc.sim.scenario import Scenario

    if args.episode_steps < 1:
        raise ConfigError(f"--episode-steps must be >= 1, got {args.episode_steps}")
    scenario = Scenario(
        n_vehicles=args.vehicles, cav_penetration=args.penetration, style_mix=args.mix
    )
    cfg = EnvConfig(
        backend=args.backend,
        map=args.map,
        use_psar=False,  # CAVs get no commands: they keep their lane and speed
        scenario=scenario,
        sim=SimConfig(style_preset=args.style_preset, episode_steps=args.episode_steps),
        obs=ObservationConfig(max_vehicles=max(ObservationConfig.max_vehicles, args.vehicles)),
    )
    driver = EpisodeDriver(Policy(), cfg)
    try:
        recorder = play_episode(driver, args.seed)
    finally:
        driver.close()
    road, version = driver.road, driver.backend.version
    print(
        f"diacc simulate: backend {args.backend}{f' ({version})' if version else ''}, "
        f"map {road.name}, N={scenario.n_vehicles} ({scenario.n_cavs} CAVs), mix {args.mix}, "
        f"style preset {args.style_preset}, seed {args.seed}, at most {args.episode_steps} steps"
    )
    kinds = tuple(dict.fromkeys(seg.kind for seg in road.segments))
    print_lines(metric_lines(recorder.summary(), kinds))


def _convert_parser(sub) -> None:
    p = cli_scale.add_command(
        sub,
        "convert-checkpoint",
        "rewrite old (format 1) checkpoints in today's format",
        "Format 1 kept numpy's RNG state as a pickled array, which a safe load\n"
        "(torch weights_only) refuses. Converting reads numpy arrays besides tensors\n"
        "and plain values, nothing else; the networks are copied bit for bit.",
    )
    p.add_argument("paths", nargs="+", type=Path, metavar="FILE", help="checkpoints to convert")
    p.add_argument(
        "--suffix",
        default="",
        help="write FILE with this suffix added to the stem (e.g. -v2) instead of in place",
    )


def cmd_convert(args: argparse.Namespace) -> None:
    from diacc.learn.checkpoint import convert_checkpoint

    for path in args.paths:
        dst = path.with_name(f"{path.stem}{args.suffix}{path.suffix}")
        print(f"converted {path} -> {convert_checkpoint(path, dst)}")


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="diacc", description=DESCRIPTION)
    parser.add_argument("--version", action="version", version=f"diacc {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _train_parser(sub)
    _bench_parser(sub)
    _simulate_parser(sub)
    _convert_parser(sub)
    cli_eval.add_parsers(sub)
    cli_scale.add_parsers(sub)
    cli_reproduce.add_parsers(sub)
    return parser


COMMANDS = {
    "train": cmd_train,
    "bench": cmd_bench,
    "simulate": cmd_simulate,
    "convert-checkpoint": cmd_convert,
    **cli_eval.COMMANDS,
    **cli_scale.COMMANDS,
    **cli_reproduce.COMMANDS,
}


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP, raised in the main thread like SIGINT's KeyboardInterrupt."""

    def __init__(self, signum: int = signal.SIGTERM) -> None:
        super().__init__()
        self.signum = signum

    def __str__(self) -> str:
        return f"terminated ({signal.Signals(self.signum).name})"


#: Signals that end a command the way SIGINT does (a closed terminal sends SIGHUP).
TERMINATING = (signal.SIGTERM, signal.SIGHUP)
#: Set by the handler: libraries that catch the exception and raise a bare
#: KeyboardInterrupt of their own (Ray's ``wait``/``get``) lose its type.
_signal_seen: int | None = None


def _terminated(signum: int, frame) -> None:
    global _signal_seen
    _signal_seen = signum
    raise Terminated(signum)


def main(argv: list[str] | None = None) -> int:
    from diacc.runlog import enable_stderr

    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # recorded by `reproduce`
    enable_stderr()
    main_thread = threading.current_thread() is threading.main_thread()
    global _signal_seen
    _signal_seen = None
    # SIGTERM and SIGHUP as SIGINT: an exception, so that every `finally` ends its
    # children (pool and vector-env workers, SUMO, a local Ray) instead of orphaning them.
    previous = {s: signal.signal(s, _terminated) for s in TERMINATING} if main_thread else {}
    try:
        return _run(args)
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def _run(args: argparse.Namespace) -> int:
    try:
        COMMANDS[args.command](args)
        sys.stdout.flush()  # here, so that a closed pipe is caught below
    except DiaccError as exc:
        if os.environ.get("DIACC_DEBUG"):
            raise
        message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        print(f"diacc: error: {message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:  # TrainingInterrupted says which signal and what was saved
        if _signal_seen and not hasattr(exc, "signum"):
            exc = Terminated(_signal_seen)
        print(f"diacc: {str(exc) or 'interrupted'}", file=sys.stderr)
        return 128 + getattr(exc, "signum", 2)
    except BrokenPipeError:
        # The reader (``diacc simulate | head``) has gone: stop quietly, as Unix tools do.
        # stdout is pointed at /dev/null so that the interpreter's final flush cannot fail.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    return 0
