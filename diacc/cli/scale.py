"""``diacc sweep``: its options and handler (registered by :mod:`diacc.cli.parser`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from diacc.cli.options import add_device_arg, add_engine_args, add_out_arg, csv_list
from diacc.config import BACKENDS, VARIANTS, ConfigError, EnvConfig, TrainConfig
from diacc.experiments.sweepaxes import STUDIES


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

    variants, maps = csv_list(args.variants), csv_list(args.maps)
    seeds = csv_list(args.seeds, int)
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
