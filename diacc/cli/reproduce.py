"""Command-line parser and handler of ``diacc reproduce`` (registered by
:mod:`diacc.cli.parser`).

Every value is checked before anything is trained or written; bad input is a
one-line ``diacc: error: ...`` with exit code 2 (list options are parsed here,
not by argparse ``choices``, so that a bad item gives one line, not a usage).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
from pathlib import Path

from diacc.cli import options
from diacc.config import (
    ACTION_MODES,
    BACKENDS,
    PAPER_VARIANTS,
    STYLE_PRESETS,
    VARIANTS,
    ConfigError,
    TrainConfig,
)
from diacc.experiments.grid import DEFAULT_STREAM, GRID_NAMES, SEED_STREAMS
from diacc.experiments.reproduce.plan import DEFAULT_GRIDS
from diacc.experiments.sweepaxes import STUDIES


def _epilog() -> str:
    import textwrap

    from diacc.experiments.reproduce.plan import BUDGET_PURPOSE, BUDGETS, describe_budget

    lines = ["budgets (explicit options override the preset's value):"]
    for name, budget in BUDGETS.items():
        text = f"{describe_budget(budget)}: {BUDGET_PURPOSE[name]}"
        lines += textwrap.wrap(text, 78, initial_indent=f"  {name:<6} ", subsequent_indent=" " * 9)
    return "\n".join(lines) + "\n\n" + LAYOUT_HELP


LAYOUT_HELP = """\
layout of --out:
  runs/<variant>-<map>-s<seed>[-<backend>][-<setting>]/   training runs
  eval/<backend>/<policy>/                    evaluation results
  tables/table2.{md,tex} table3.{md,tex}      Tables II (training grid), III (the paper's
                                              zero-shot rows; table3-product: the product grid)
  figures/curves-<map>.png  speeds-<backend>-<map>.png   (and .pdf)
  transfer.md transfer.csv                    sim-to-sim transfer
  manifest.json                               invocations, versions, plan, stages

Re-running the same command continues a killed reproduction (training resumes
from checkpoints, finished evaluation cells are skipped) and re-checks a
finished one in seconds."""


def add_parsers(sub) -> None:
    p = sub.add_parser(
        "reproduce",
        help="train, evaluate and tabulate the paper's experiments in one resumable command",
        description="Train the variants on the training maps for every seed, evaluate every\n"
        "checkpoint and the pure-hdv, same-mix, cooperative and heuristic baselines on\n"
        "the training and zero-shot grids on both backends, and write Tables II and\n"
        "III, the training curves, the speed distributions and the sim-to-sim\n"
        "transfer report.\n"
        "Prints the resolved plan first, one line per run and evaluation job, and\n"
        "where the files are at the end.",
        epilog=_epilog(),
    )
    p.add_argument("--out", type=Path, default=Path("results/reproduce"), help="results folder")
    p.add_argument("--budget", default="paper", help="tiny, small or paper (see below)")
    p.add_argument(
        "--steps",
        type=int,
        default=None,
        help="environment steps per training run (decisions x environments)",
    )
    p.add_argument("--seeds", default=None, help="comma-separated run seeds, e.g. 1,2,3")
    p.add_argument("--envs", type=int, default=None, help="environments per training run")
    p.add_argument("--episodes", type=int, default=None, help="evaluation episodes per cell")
    p.add_argument("--maps", default=None, help="comma-separated training maps")
    p.add_argument(
        "--zero-shot-cells",
        type=int,
        default=None,
        help="zero-shot cells kept per test map, evenly spread (0: all)",
    )
    p.add_argument(
        "--transfer",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="also train diacc on sumo and compare both on sumo (default: the budget's)",
    )
    p.add_argument(
        "--variants",
        default=",".join(PAPER_VARIANTS),
        help=f"comma-separated variants to train, of {', '.join(VARIANTS)}; the paper's four",
    )
    p.add_argument(
        "--backends", default=",".join(BACKENDS), help="comma-separated backends to evaluate on"
    )
    p.add_argument("--train-backend", default="highway", help="backend the variants train on")
    p.add_argument(
        "--grids",
        default=",".join(DEFAULT_GRIDS),
        help=f"comma-separated, of {', '.join(GRID_NAMES)} (zero-shot: the paper's rows)",
    )
    p.add_argument(
        "--style-preset",
        default="realistic",
        help=f"HDV style preset for training and evaluation: {', '.join(STYLE_PRESETS)}",
    )
    p.add_argument(
        "--episode-steps",
        type=int,
        default=None,
        help="decisions per evaluation episode (default: the policy's own, 100)",
    )
    p.add_argument(
        "--actions",
        choices=ACTION_MODES,
        default="greedy",
        help="checkpoints' evaluation actions: argmax, or sampled from their distribution "
        "(seeded per episode)",
    )
    p.add_argument(
        "--stream",
        choices=SEED_STREAMS,
        default=None,
        help="evaluation seed stream (default: validation with --sweep/--study, which choose "
        "a setting, test otherwise; see 'diacc eval --help')",
    )
    options.add_device_arg(p, "torch device of every training run's PPO update")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="training config override as in 'diacc train' (repeatable), e.g. "
        "torch_threads=2 when --jobs runs share a machine",
    )
    p.add_argument(
        "--sweep",
        action="append",
        default=[],
        metavar="KEY=V1,V2",
        help="train every variant with each of these config values, as in 'diacc sweep' "
        "(repeatable: the product); one table column and curve per setting",
    )
    p.add_argument(
        "--study",
        default=None,
        help=f"one of the paper's selection studies as a --sweep axis: {', '.join(STUDIES)} "
        "(see 'diacc sweep --help')",
    )
    p.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="local worker processes: training runs in parallel, and evaluation workers",
    )
    p.add_argument("--cpus-per-run", type=float, default=1.0, help="CPUs Ray reserves per run")
    p.add_argument("--dry-run", action="store_true", help="print the plan and stop")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    options.add_engine_args(p)


def _names(text: str) -> tuple[str, ...]:
    return tuple(options.csv_list(text))


def cmd_reproduce(args: argparse.Namespace) -> None:
    from diacc.experiments.evaluate import MAX_WORKERS
    from diacc.experiments.reproduce.pipeline import reproduce
    from diacc.experiments.reproduce.plan import Execution, describe_plan, make_plan, resolve_config
    from diacc.experiments.sweepaxes import axis_texts, sweep_settings

    if not 1 <= args.jobs <= MAX_WORKERS:
        raise ConfigError(
            f"--jobs must be in [1, {MAX_WORKERS}], got {args.jobs} (each is a process with "
            "its own simulator and torch, about 0.4 GB)"
        )
    if args.engine == "local" and (args.ray_address or args.ray_cpus):
        raise ConfigError("--ray-address / --ray-cpus need --engine ray")
    config, notes = resolve_config(
        args.budget,
        steps=args.steps,
        seeds=None if args.seeds is None else tuple(options.csv_list(args.seeds, int)),
        envs=args.envs,
        episodes=args.episodes,
        maps=None if args.maps is None else _names(args.maps),
        zero_shot_cells=args.zero_shot_cells,
        transfer=args.transfer,
        out_dir=args.out,
        variants=_names(args.variants),
        backends=_names(args.backends),
        train_backend=args.train_backend,
        grids=_names(args.grids),
        style_preset=args.style_preset,
        episode_steps=args.episode_steps,
        actions=args.actions,
        device=args.device or TrainConfig.device,
        train_sets=tuple(args.set),
    )
    plan = make_plan(config, notes)
    # one-line error for a bad --set or --sweep before anything runs
    base = plan.train_config(plan.runs[0])
    axes = axis_texts(args.sweep, args.study)
    # A sweep chooses among its settings: on validation episodes, never on test ones.
    stream = args.stream or ("validation" if axes else DEFAULT_STREAM)
    config = dataclasses.replace(config, stream=stream)
    settings = tuple(sweep_settings(base, axes)) if axes else ()
    plan = make_plan(dataclasses.replace(config, settings=settings), notes)
    say = functools.partial(print, flush=True)
    for line in describe_plan(plan):
        say(line)
    if args.dry_run:
        return
    execution = Execution(
        jobs=args.jobs,
        engine=args.engine,
        ray_address=args.ray_address,
        ray_cpus=args.ray_cpus,
        cpus_per_run=args.cpus_per_run,
        progress=not args.no_progress,
    )
    produced = reproduce(plan, execution, ["diacc", *args.argv], say)
    for line in produced.summary():
        say(line)


COMMANDS = {"reproduce": cmd_reproduce}
