"""Command-line options of the scale-out engines and ``diacc sweep``, and the
parser helpers every command module shares (:func:`add_command`, :func:`add_out_arg`).

Registered by :mod:`diacc.cli`; ``diacc eval`` takes the engine options too.
Ray is imported only when ``--engine ray`` is chosen (:mod:`diacc.experiments.scaleout`).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from diacc.config import BACKENDS, VARIANTS, ConfigError, EnvConfig, TrainConfig
from diacc.experiments.sweepaxes import STUDIES

#: ``--device`` choices: those of :attr:`TrainConfig.device <diacc.config.TrainConfig>`.
DEVICES = next(f for f in dataclasses.fields(TrainConfig) if f.name == "device").metadata["choices"]


def add_command(sub, name: str, summary: str, description: str = "") -> argparse.ArgumentParser:
    """A subcommand whose ``--help`` starts with its summary (and description):
    the list of commands and each command's own help then say the same."""
    text = summary[0].upper() + summary[1:] + "." + (f"\n\n{description}" if description else "")
    return sub.add_parser(name, help=summary, description=text)


def add_renamed_arg(p: argparse.ArgumentParser, name: str, old_name: str, **kwargs) -> None:
    """Option ``name`` and ``old_name`` (its former spelling) as a hidden alias of the
    same ``dest``, so that old command lines still run while ``--help`` shows one name
    per meaning. Give ``dest``: argparse would derive the alias's own from its name."""
    p.add_argument(name, **kwargs)
    alias = {k: v for k, v in kwargs.items() if k != "default"}
    p.add_argument(old_name, **{**alias, "help": argparse.SUPPRESS, "default": argparse.SUPPRESS})


def add_out_arg(p: argparse.ArgumentParser, old_name: str, **kwargs) -> None:
    """``--out``, every command's name for where it writes, with ``old_name`` (the
    command's former name for it) as a hidden alias (:func:`add_renamed_arg`)."""
    add_renamed_arg(p, "--out", old_name, **kwargs)


def add_device_arg(
    p: argparse.ArgumentParser, what: str = "torch device of the PPO update"
) -> None:
    """``--device``, the same choices and default on every command: None, which stands
    for :attr:`TrainConfig.device <diacc.config.TrainConfig>` (``auto``) unless a
    ``--config`` file names another, so that ``train``, ``sweep``, ``reproduce`` and
    ``bench`` pick the same device for the same command line."""
    p.add_argument(
        "--device",
        choices=DEVICES,
        default=None,
        help=f"{what}; auto: cuda if this machine has it, else cpu (TrainConfig's default, "
        f"so that every command picks the same device) (default: {TrainConfig.device})",
    )


def add_engine_args(p: argparse.ArgumentParser) -> None:
    """``--engine``, ``--ray-address``, ``--ray-cpus``."""
    p.add_argument(
        "--engine",
        choices=("local", "ray"),
        default="local",
        help="local: processes on this machine; ray: Ray tasks (pip install -e '.[ray]')",
    )
    p.add_argument(
        "--ray-address",
        default=None,
        help="Ray cluster to join (auto, HOST:6379 or ray://HOST:10001); "
        "default: start a local Ray instance",
    )
    p.add_argument(
        "--ray-cpus",
        type=int,
        default=None,
        help="CPUs of the local Ray instance (default: all of this machine's)",
    )


def eval_engine(args: argparse.Namespace):
    """The evaluation engine the options ask for (None: the local worker pool)."""
    if args.engine == "local":
        if args.ray_address or args.ray_cpus:
            raise ConfigError("--ray-address / --ray-cpus need --engine ray")
        return None
    from diacc.experiments.scaleout import RayEngine

    return RayEngine(args.ray_address, args.ray_cpus)


def seed_type(text: str) -> int:
    """An argparse type: a traffic seed, a whole number in [0, 2^32 - 1] (numpy's range)."""
    try:
        seed = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if not 0 <= seed < 2**32:
        raise argparse.ArgumentTypeError(f"must be in [0, 2^32 - 1], got {seed}")
    return seed


def _csv_list(text: str, kind=str) -> list:
    try:
        values = [kind(v.strip()) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ConfigError(
            f"expected a comma-separated list of {kind.__name__}, got {text!r}"
        ) from None
    if not values:
        raise ConfigError(f"expected a comma-separated list, got {text!r}")
    return values


def add_parsers(sub) -> None:
    p = sub.add_parser(
        "sweep",
        help="train variants x maps x config settings x seeds, locally or as Ray tasks",
        description="Train every (variant, map, setting, seed) combination, one run directory\n"
        "each (<out>/<variant>-<backend>-<map>-s<seed>[-<setting>]), then draw\n"
        "<out>/curves-<map>.png: one curve per variant and setting, mean +- std\n"
        "over seeds. Settings come from --sweep KEY=V1,V2 (repeatable: the product)\n"
        "and --study. Finished runs are skipped, interrupted ones resume from their\n"
        "checkpoint, a directory holding a run with other settings is an error. With\n"
        "--engine ray the runs are parallel Ray tasks; on a cluster, put --out on\n"
        "a shared filesystem. Other settings as in 'diacc train' (--config, --set;\n"
        "the sweep axes win).",
        epilog="studies (the paper's training-curve figure, panels d-i):\n"
        + "\n".join(f"  {name:<4} --sweep {axis}" for name, axis in STUDIES.items())
        + "\n\nKEY1,KEY2=A1:B1,A2:B2 moves two keys together (a fixed tau is\n"
        "tau_init = tau_final; the w_e study keeps w_g = 1 - w_e).",
    )
    p.add_argument(
        "--sweep",
        action="append",
        default=[],
        metavar="KEY=V1,V2",
        help="config values to train, e.g. env.reward.tau_final=0.05,0.5 (repeatable: product)",
    )
    p.add_argument(
        "--study",
        default=None,
        help=f"one of the paper's selection studies as a --sweep axis: {', '.join(STUDIES)}",
    )
    p.add_argument("--variants", default="diacc", help=f"comma-separated, of {', '.join(VARIANTS)}")
    p.add_argument("--maps", default=EnvConfig.map, help="comma-separated map names or paths")
    p.add_argument("--seeds", default="1,2,3", help="comma-separated run seeds")
    # None: the --config file's value, else the default the help names (as in 'diacc train')
    p.add_argument(
        "--backend",
        choices=BACKENDS,
        default=None,
        help=f"simulator (default: {EnvConfig.backend})",
    )
    p.add_argument(
        "--steps",
        type=int,
        default=None,
        help="environment steps per run (decisions x environments) "
        f"(default: {TrainConfig.total_steps})",
    )
    p.add_argument(
        "--envs",
        type=int,
        default=None,
        help=f"environments per run (default: {TrainConfig.n_envs})",
    )
    add_device_arg(p, "torch device of each run's PPO update")
    add_out_arg(
        p,
        "--out-dir",
        dest="out",
        metavar="DIR",
        type=Path,
        default=Path("runs/sweep"),
        help="parent of the run dirs",
    )
    p.add_argument(
        "--config",
        type=Path,
        help="TOML file of config overrides (none by default), e.g. configs/paper-learner.toml",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override any config field (repeatable)",
    )
    p.add_argument("--cpus-per-run", type=float, default=1.0, help="CPUs Ray reserves for each run")
    add_engine_args(p)


def cmd_sweep(args: argparse.Namespace) -> None:
    from diacc.config import build_train_config
    from diacc.console import fmt, plural, print_config
    from diacc.experiments.plots import plot_curves
    from diacc.experiments.scaleout import check_run_dirs, run_sweep, sweep_configs
    from diacc.experiments.sweepaxes import axis_texts, sweep_settings
    from diacc.sim.maps import load_map

    variants, maps = _csv_list(args.variants), _csv_list(args.maps)
    seeds = _csv_list(args.seeds, int)
    for variant in variants:
        if variant not in VARIANTS:
            raise ConfigError(f"unknown variant {variant!r}; use some of {', '.join(VARIANTS)}")
    for map_name in maps:
        load_map(map_name)  # fail fast on a bad map name
    # the first run's settings; sweep_configs sets each run's variant, map, seed and run_dir
    base = build_train_config(
        args.config,
        variant=variants[0],
        backend=args.backend,
        map=maps[0],
        steps=args.steps,
        envs=args.envs,
        seed=seeds[0],
        device=args.device,
        run_dir=args.out,
        sets=args.set,
    )
    if args.engine == "local" and (args.ray_address or args.ray_cpus):
        raise ConfigError("--ray-address / --ray-cpus need --engine ray")
    settings = sweep_settings(base, axis_texts(args.sweep, args.study))
    configs = sweep_configs(base, variants, maps, seeds, args.out, settings)
    check_run_dirs(configs)
    # sweep_configs' order is variant, map, setting, seed: one setting per len(seeds) runs
    label = {
        cfg.run_dir: settings[(i // len(seeds)) % len(settings)].label
        for i, cfg in enumerate(configs)
    }
    print_config(
        base,
        f"diacc sweep: {len(configs)} runs ({len(variants)} variants x {len(maps)} maps x "
        + (f"{plural(len(settings), 'setting')} x " if settings[0].values else "")
        + f"{len(seeds)} seeds) on engine {args.engine}; shared config",
        "variant, map, setting, seed and run_dir vary per run",
    )
    for setting in settings:
        if setting.values:
            print(f"  setting {setting.label}")
    for n, run in enumerate(
        run_sweep(configs, args.engine, args.ray_address, args.ray_cpus, args.cpus_per_run), 1
    ):
        setting = f" {label[run.run_dir]}" if label[run.run_dir] else ""
        print(
            f"[{n}/{len(configs)}] {run.status} {run.variant} {run.map}{setting} seed {run.seed}"
            f"{f' on {run.host}' if run.host else ''}"
            f"{f' in {run.wall_s:.1f} s' if run.wall_s else ''}: {run.run_dir}; last update: "
            f"collision rate {fmt(run.last.get('episode/collision'))}, "
            f"team reward {fmt(run.last.get('team_reward'))}"
        )
    for map_name in maps:
        # Ray runs on other machines write their directories there (no shared filesystem)
        runs = [c.run_dir for c in configs if c.env.map == map_name]
        here = [r for r in runs if (Path(r) / "progress.jsonl").exists()]
        if len(here) < len(runs):
            print(f"training curves of {map_name}: {len(runs) - len(here)} run dirs not here")
        if here:
            paths = plot_curves(here, args.out / f"curves-{Path(map_name).stem}")
            print(f"training curves: {paths[0]}")


COMMANDS = {"sweep": cmd_sweep}
