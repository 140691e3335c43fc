"""``diacc bench``: its options and handler, which picks the benchmarks of
:mod:`diacc.experiments.bench` (registered by :mod:`diacc.cli.parser`)."""

from __future__ import annotations

import argparse

from diacc.cli.options import add_command, add_device_arg
from diacc.config import (
    BACKENDS,
    HIGHWAY_MERGES,
    HORIZON_MODES,
    STYLE_PRESETS,
    ConfigError,
    SimConfig,
    TrainConfig,
)
from diacc.sim.scenario import SCENARIO_KINDS


def add_parsers(sub) -> None:
    p = add_command(
        sub,
        "bench",
        "speed benchmarks, measured side by side in one run",
        "Choose at least one of --backend, --models, --training, --env-batch, --safety, "
        "--headway, --headroom, --fidelity, --agent-slots.",
    )
    p.add_argument("--backend", choices=BACKENDS, help="backend vs its reference simulator loop")
    p.add_argument("--models", action="store_true", help="network sizes and forward/update times")
    p.add_argument("--training", action="store_true", help="end-to-end training env-steps/s")
    p.add_argument(
        "--agent-slots",
        action="store_true",
        help="a cap of 16 agent slots vs every CAV an agent: rollout and update seconds, "
        "decisions, buffer bytes per slot and per critic row (demand 3600 veh/h, highway)",
    )
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
        help="style preset of --safety / --headway / --headroom / --fidelity (default: each one's)",
    )
    p.add_argument(
        "--highway-merges",
        choices=HIGHWAY_MERGES,
        default=None,
        help="how the highway backend's drivers leave an ending lane, in --fidelity "
        "(default: late; early matches SUMO's capacity)",
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
    add_device_arg(p, "torch device of --models and the PPO update of --training and --agent-slots")
    # --steps, the former name of both --timing-steps and --headway / --headroom's
    # --episode-steps: hidden, still accepted (cmd_bench gives it the meaning it had)
    p.add_argument("--steps", dest="legacy_steps", type=int, default=None, help=argparse.SUPPRESS)


def bench_device(name: str | None) -> str:
    """The concrete torch device (``cpu``, ``cuda``) of ``--device``, so that the
    benchmark tables name the device they measured, not ``auto``."""
    from diacc.learn.trainer import resolve_device

    return str(resolve_device(name or TrainConfig.device))


def bench_lengths(args: argparse.Namespace) -> None:
    """Give ``bench``'s hidden ``--steps`` the meaning it had before it was split
    (checked by :class:`~diacc.experiments.bench.options.BenchOptions`): episode steps of
    --headway / --headroom, else steps to time (--safety ignored it); the new names win
    where both are given."""
    if args.legacy_steps is None or args.safety:
        return
    if args.headway or args.headroom:
        args.episode_steps = args.episode_steps or args.legacy_steps
    else:
        args.timing_steps = args.timing_steps or args.legacy_steps


def cmd_bench(args: argparse.Namespace) -> None:
    from diacc.experiments.bench.options import BenchOptions

    ran = False
    BenchOptions.of(args)  # every shared option and their relations, checked in one place
    bench_lengths(args)
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
        preset = {"preset": args.style_preset, "highway_merges": args.highway_merges}
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
        if args.scenario == "demand":  # one --inflow (BenchOptions)
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
    if args.agent_slots:
        from diacc.experiments.bench import slots

        slots.run(device=bench_device(args.device))
        ran = True
    if args.env_batch:
        from diacc.experiments.bench import envbatch

        envbatch.run(**({"steps": args.timing_steps} if args.timing_steps else {}))
        ran = True
    if not ran:
        raise ConfigError(
            "choose what to benchmark: --backend highway|sumo, --models, --training, "
            "--env-batch, --agent-slots, --safety, --headway or --headroom"
        )


COMMANDS = {"bench": cmd_bench}
