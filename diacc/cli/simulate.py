"""``diacc simulate``: one episode of human-driven traffic, no policy (registered by
:mod:`diacc.cli.parser`)."""

from __future__ import annotations

import argparse

from diacc.cli.options import add_command, add_renamed_arg, seed_type
from diacc.config import (
    BACKENDS,
    HIGHWAY_MERGES,
    STYLE_PRESETS,
    ConfigError,
    EnvConfig,
    SimConfig,
)


def add_parsers(sub) -> None:
    p = add_command(
        sub,
        "simulate",
        "simulate one episode of human-driven traffic and print its metrics",
        "HDVs drive themselves (IDM + MOBIL on highway, IDM + LC2013 on SUMO); CAVs,\n"
        "if --penetration > 0, get no commands and keep their lane and speed. To\n"
        "run a trained policy or the cooperative baseline, use 'diacc eval'.",
    )
    p.add_argument("--backend", choices=BACKENDS, default="highway", help="simulator")
    p.add_argument(
        "--map",
        default="train-25",
        help="shipped map name, generated one (gen-test-7) or .toml path",
    )
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
    p.add_argument(
        "--highway-merges",
        choices=HIGHWAY_MERGES,
        default=None,
        help="how the highway backend's drivers leave an ending lane (early: SUMO's capacity) "
        "(default: late)",
    )
    add_renamed_arg(
        p,
        "--episode-steps",
        "--steps",  # its former name
        dest="episode_steps",
        type=int,
        default=150,
        help="decision steps (1 s) at most",
    )
    p.add_argument("--seed", type=seed_type, default=0, help="traffic seed")


def cmd_simulate(args: argparse.Namespace) -> None:
    from diacc.config import ObservationConfig
    from diacc.console import metric_lines, print_lines
    from diacc.envs.episode import EpisodeDriver, play_episode
    from diacc.experiments.policies import Policy
    from diacc.sim.scenario import Scenario
    from diacc.sim.settings import check_merges_backend

    if args.episode_steps < 1:
        raise ConfigError(f"--episode-steps must be >= 1, got {args.episode_steps}")
    check_merges_backend(args.backend, args.highway_merges)
    merge_model = args.highway_merges or SimConfig.highway_merges
    scenario = Scenario(
        n_vehicles=args.vehicles, cav_penetration=args.penetration, style_mix=args.mix
    )
    cfg = EnvConfig(
        backend=args.backend,
        map=args.map,
        use_psar=False,  # CAVs get no commands: they keep their lane and speed
        scenario=scenario,
        sim=SimConfig(
            style_preset=args.style_preset,
            episode_steps=args.episode_steps,
            highway_merges=merge_model,
        ),
        obs=ObservationConfig(max_vehicles=max(ObservationConfig.max_vehicles, args.vehicles)),
    )
    driver = EpisodeDriver(Policy(), cfg)
    try:
        recorder = play_episode(driver, args.seed)
    finally:
        driver.close()
    road, version = driver.road, driver.backend.version
    merges = f", {merge_model} merges" if args.backend == "highway" else ""
    print(
        f"diacc simulate: backend {args.backend}{f' ({version})' if version else ''}, "
        f"map {road.name}, N={scenario.n_vehicles} ({scenario.n_cavs} CAVs), mix {args.mix}, "
        f"style preset {args.style_preset}{merges}, seed {args.seed}, at most "
        f"{args.episode_steps} steps"
    )
    kinds = tuple(dict.fromkeys(seg.kind for seg in road.segments))
    print_lines(metric_lines(recorder.summary(), kinds))


COMMANDS = {"simulate": cmd_simulate}
