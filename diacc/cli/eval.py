"""Command-line parsers and handlers for ``diacc eval | table | plot | render | scorecard``.

Registered by :mod:`diacc.cli.parser` (``add_parsers`` and ``COMMANDS``); errors are
the one-line exceptions of the modules they call.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from diacc.cli import options
from diacc.config import (
    ACTION_MODES,
    BACKENDS,
    FULL_BRAKE_MODES,
    HIGHWAY_MERGES,
    HORIZON_MODES,
    ON_COLLISION,
    STYLE_PRESETS,
    ConfigError,
)
from diacc.experiments.evalsettings import AGENT_SLOTS
from diacc.experiments.grid import DEFAULT_STREAM, SEED_STREAMS
from diacc.experiments.userpolicy import DEFAULT_TIMEOUT_S
from diacc.fileio import OutputPathError, atomic_write, check_output_file
from diacc.sim.scenario import EVERY_CAV

#: How ``diacc table`` marks entries (the rule of :mod:`diacc.experiments.report`, kept here so
#: that ``--help`` does not import the evaluation stack).
TABLE_RULES = """\
Per row the best value is bold and the second best underlined (italic in
Markdown), as in the paper's Tables II/III, compared at the printed precision.
A column is ranked in a cell only if it is no slower than the pure-HDV column
(same backend) and has no higher collision rate; a policy slower or crashing
more than human traffic is never marked best. Entries show the change against
pure HDV and against same-mix; the latter paired by episode seed (the same
traffic) with its 95 % bootstrap interval [low, high], marked "≈" (no
measurable difference) where the interval holds 0. LaTeX output needs
\\usepackage{booktabs} and \\usepackage{multirow}."""


def _settings(args: argparse.Namespace):
    from diacc.experiments.policies import EvalSettings

    return EvalSettings(
        backend=args.backend,
        episode_steps=args.episode_steps,
        style_preset=args.style_preset,
        psar_horizon=args.psar_horizon,
        psar_full_brake=args.psar_full_brake,
        highway_merges=args.highway_merges,
        agent_slots=args.agent_slots,
        on_collision=args.on_collision,
        stream=args.stream,
        controller_timeout_s=args.controller_timeout,
    )


def _policy_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--policy",
        required=True,
        help="pure-hdv, same-mix (CAV slots driven by normal human drivers; same-mix:<style> "
        "for aggressive or cautious ones), cooperative, heuristic, a scripted probe "
        "(remain, accelerate, random, late-merge; <name>-nopsar without PSAR), a checkpoint.pt "
        "(or its run directory), or your own controller as package.module:factory "
        "(examples/keep_right_controller.py)",
    )
    p.add_argument(
        "--variant",
        default=None,
        help="require the checkpoint to be of this variant (any by default)",
    )
    p.add_argument(
        "--actions",
        choices=ACTION_MODES,
        default="greedy",
        help="a checkpoint's actions: argmax, or sampled from its distribution (seeded)",
    )
    p.add_argument("--backend", choices=BACKENDS, default="highway", help="simulator")
    p.add_argument(
        "--episode-steps",
        type=int,
        default=None,
        help="decisions per episode (default: the policy's own setting, 100)",
    )
    p.add_argument(
        "--style-preset",
        choices=tuple(STYLE_PRESETS),
        default=None,
        help="HDV style preset (default: the policy's own setting)",
    )
    p.add_argument(
        "--psar-horizon",
        choices=HORIZON_MODES,
        default=None,
        help="PSAR horizon of every policy with PSAR, baselines and checkpoints alike "
        "(default: the policy's own setting; docs/concepts/psar.md)",
    )
    p.add_argument(
        "--psar-full-brake",
        choices=FULL_BRAKE_MODES,
        default=None,
        help="when PSAR's headway car following may brake beyond the planned rate, for every "
        "policy with PSAR (default: the policy's own setting; docs/concepts/psar.md)",
    )
    p.add_argument(
        "--highway-merges",
        choices=HIGHWAY_MERGES,
        default=None,
        help="how the highway backend's human drivers leave an ending lane: late (200 m "
        "before its end) or early (400 m; passes SUMO's capacity within 10 %%) (default: "
        "the policy's own setting)",
    )
    p.add_argument(
        "--agent-slots",
        type=options.slots_type(*AGENT_SLOTS),
        default=EVERY_CAV,
        metavar="{every,own,N}",
        help="agent slots in a demand cell: every CAV one (none drives itself), "
        "the policy's own cav_slots (a checkpoint's from training), or a cap N on the CAVs "
        "it drives at once; with a cap, CAVs beyond it drive themselves",
    )
    p.add_argument(
        "--on-collision",
        choices=ON_COLLISION,
        default="remove",
        help="what a collision does: remove the vehicles that collided and run on to the "
        "episode's end (default: a crash cannot shorten the episode that delay and "
        "throughput average over) or end the episode (training's rule, and every result "
        "recorded before 2026-12-06; docs/concepts/baselines.md)",
    )
    p.add_argument(
        "--controller-timeout",
        type=float,
        default=DEFAULT_TIMEOUT_S,
        metavar="SECONDS",
        help="longest one act() or reset() call of your own controller may run before the "
        "command stops with an error naming cell and step (0: no limit)",
    )
    p.add_argument(
        "--stream",
        choices=SEED_STREAMS,
        default=DEFAULT_STREAM,
        help="episode seed stream: test (to report), validation (to choose seeds, settings, "
        "checkpoints on; disjoint from test) or legacy (the stream of older results)",
    )


def add_parsers(sub) -> None:
    """Add the evaluation subcommands to the main parser."""
    p = options.add_command(
        sub,
        "eval",
        "evaluate a policy or baseline on a grid of scenarios",
        "Writes episodes.csv and speeds.csv.gz into --out; re-running skips finished cells.\n"
        "Episode seeds depend on the seed stream, cell and episode only, so every policy\n"
        "meets the same traffic.",
    )
    _policy_args(p)
    p.add_argument(
        "--grid",
        default="train",
        help="train (paper training cells), zero-shot (the paper's zero-shot rows), "
        "zero-shot-product (32 test-map cells of our own), or a grid .toml file",
    )
    p.add_argument("--episodes", type=int, default=10, help="seeded episodes per cell")
    p.add_argument("--out", required=True, type=Path, help="results directory (required)")
    p.add_argument("--workers", type=int, default=1, help="local worker processes (spawn)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    options.add_engine_args(p)

    p = options.add_command(
        sub, "table", "paper-style table (Tables II/III) from results directories", TABLE_RULES
    )
    p.add_argument("results", nargs="+", type=Path, help="results directories, one per column")
    p.add_argument(
        "--format", choices=("markdown", "latex", "csv"), default="markdown", help="output format"
    )
    p.add_argument(
        "--speed-std",
        choices=("samples", "episodes"),
        default="samples",
        help="speed std over all vehicle-steps (paper) or over episode means",
    )
    p.add_argument(
        "--rows",
        default="speed,p_we,p_sce",
        help="comma-separated rows: speed, p_we, p_sce (the paper's) and the optional "
        "collision (share of episodes ending in a crash), arrived (share of vehicles) and the "
        "flow rows throughput, delay, arrived_speed, travel_time, never_arrived "
        "('flow' stands for all five)",
    )
    p.add_argument(
        "--paired-against",
        default="same-mix",
        metavar="POLICY|DIR",
        help="the column whose changes are paired by episode seed with a 95 %% interval: a "
        "policy (another than same-mix, e.g. heuristic, adds its change to every entry) or "
        "one of the results directories (to compare checkpoints, which share a policy name)",
    )
    p.add_argument("--out", type=Path, default=None, help="write to a file instead of stdout")

    p = options.add_command(
        sub,
        "scorecard",
        "a policy through the standard suite against same-mix, the heuristic and DIACC",
        "Evaluates --policy and the three references on every cell of the suites\n"
        "(train, zero-shot, geometry, generated, paper-congestion, demand) and\n"
        "backends, on the test seed stream (--stream validation to choose on), 330-step\n"
        "episodes, PSAR headway / known; writes scorecard.md and scorecard.json\n"
        "(changes paired by episode seed, 95 % bootstrap intervals) into --out. Run\n"
        "from the repository root (the geometry maps and the shipped agent live\n"
        "there). Resumable: finished cells are skipped.\n"
        "Several --policy (a recipe's seeds): every seed's entries, in how many seeds\n"
        "each cell is better / worse, and the seeds' episodes pooled; never a best seed.",
    )
    p.add_argument(
        "--policy",
        required=True,
        action="append",
        help="the policy to score: any --policy of 'diacc eval' (a checkpoint, a baseline, "
        "package.module:factory); repeat it for the seeds of a recipe (each scored on its "
        "own, the references once; with their agreement and pooled episodes)",
    )
    p.add_argument(
        "--actions",
        choices=ACTION_MODES,
        default="greedy",
        help="a checkpoint's actions (every --policy's)",
    )
    p.add_argument("--episodes", type=int, default=30, help="seeded episodes per cell")
    p.add_argument(
        "--suites",
        default="all",
        help="comma-separated suites of train, zero-shot, geometry, generated, paper-congestion, "
        "demand; "
        "or all",
    )
    p.add_argument("--backends", default="highway,sumo", help="comma-separated backends")
    p.add_argument(
        "--agent",
        default=None,
        help="the DIACC agent compared with (default: the shipped "
        "checkpoints/diacc-train50-realistic-headway-threat-s1.pt)",
    )
    p.add_argument("--episode-steps", type=int, default=330, help="decisions per episode")
    p.add_argument(
        "--stream",
        choices=("test", "validation"),
        default="test",
        help="episode seeds and generated maps: test (to report) or validation (to choose "
        "a recipe's checkpoints and seeds on: its own seeds, gen-validation-* maps)",
    )
    p.add_argument("--workers", type=int, default=1, help="local worker processes (spawn)")
    p.add_argument("--out", required=True, type=Path, help="results directory (required)")

    p = options.add_command(sub, "plot", "training curves, speed distributions or flow (PNG + PDF)")
    plot_sub = p.add_subparsers(dest="plot_kind", required=True, metavar="KIND")
    q = plot_sub.add_parser(
        "curves",
        help="collision rate, global and individual reward",
        description="Collision rate, global and individual reward against environment\n"
        "steps: mean over the seeds of each variant, band = min..max over seeds.",
    )
    q.add_argument("runs", nargs="+", type=Path, help="run directories (seeds of a variant group)")
    q.add_argument(
        "--out", type=Path, default=Path("figures/curves"), help="output path, .png and .pdf added"
    )
    q.add_argument("--smooth", type=int, default=1, help="moving-average window (updates)")
    q = plot_sub.add_parser(
        "speeds",
        help="per-segment speed box plots and KDEs",
        description="Per-segment-kind speed box plots and KDEs, one colour per policy.",
    )
    q.add_argument("results", nargs="+", type=Path, help="results directories")
    q.add_argument(
        "--out", type=Path, default=Path("figures/speeds"), help="output path, .png and .pdf added"
    )
    q.add_argument("--map", default=None, help="only the samples of this map (all by default)")
    q = plot_sub.add_parser(
        "flow",
        help="outflow and delay against inflow (demand cells)",
        description="Outflow and delay per vehicle against inflow, one line per policy\n"
        "and one column per backend, with 95 % bootstrap intervals over episodes,\n"
        "outflow = inflow, and the pure-HDV capacity and its drop where a series is\n"
        "named pure-hdv (diacc.experiments.flowplot).",
    )
    q.add_argument(
        "results",
        nargs="+",
        type=Path,
        help="diacc eval results directories of demand cells, or folders holding them "
        "(<series>/q<inflow>/ as benchmarks/studies/demand-training/flow.sh writes)",
    )
    q.add_argument(
        "--out", type=Path, default=Path("figures/flow"), help="output path, .png and .pdf added"
    )
    q = plot_sub.add_parser(
        "timespace",
        help="time-space diagram and speed profile of one episode",
        description="Time-space diagram of one episode (one dot per vehicle and step,\n"
        "coloured by speed, lane reduction shaded) and its speed profile along the road.",
    )
    _policy_args(q)
    _episode_args(q)
    q.add_argument(
        "--out",
        type=Path,
        default=Path("figures/timespace"),
        help="output path, .png and .pdf added",
    )

    p = sub.add_parser(
        "render",
        help="one episode as a GIF",
        description="One episode as a GIF, with a legend and a time / step / PSAR stamp.",
    )
    _policy_args(p)
    _episode_args(p)
    p.add_argument("--fps", type=float, default=5.0, help="GIF frames per second")
    p.add_argument(
        "--view",
        choices=("traffic", "bottleneck"),
        default="traffic",
        help="camera: follow the traffic (4 px/m), or stay on the lane drop (8 px/m)",
    )
    p.add_argument("--out", type=Path, default=Path("episode.gif"), help="output .gif")


def _episode_args(p: argparse.ArgumentParser) -> None:
    """The traffic of one episode (``render``, ``plot timespace``); its length is
    ``--episode-steps`` (:func:`_policy_args`), formerly ``--steps``: still accepted."""
    p.add_argument(
        "--map",
        default="train-25",
        help="shipped map name, generated one (gen-test-7) or .toml path",
    )
    p.add_argument("--vehicles", type=int, default=25, help="vehicles inserted at t = 0 (N)")
    p.add_argument("--penetration", type=float, default=0.4, help="CAV share rho")
    p.add_argument("--mix", default="D1", help="HDV style mix: D1, D2 or D3")
    p.add_argument(
        "--steps", dest="episode_steps", type=int, default=argparse.SUPPRESS, help=argparse.SUPPRESS
    )
    p.add_argument(
        "--seed",
        type=options.seed_type,
        default=None,
        help="traffic seed (default: episode 0 of --stream)",
    )


def _episode_cell(args: argparse.Namespace):
    from diacc.experiments.grid import make_cell

    traffic = {
        "map": args.map,
        "n_vehicles": args.vehicles,
        "cav_penetration": args.penetration,
        "style_mix": args.mix,
    }
    return make_cell(traffic, args.command)


def cmd_eval(args: argparse.Namespace) -> None:
    from diacc.experiments.evaluate import evaluate
    from diacc.experiments.grid import load_grid
    from diacc.experiments.policies import parse_policy

    spec = parse_policy(args.policy, args.variant, args.actions == "sampled")
    cells = load_grid(args.grid)
    summary = evaluate(
        spec,
        cells,
        args.episodes,
        args.out,
        _settings(args),
        workers=args.workers,
        progress=not args.no_progress,
        engine=options.eval_engine(args),
    )
    print(
        f"{len(summary.cells_run)} cells run, {len(summary.cells_skipped)} already done; "
        f"results in {summary.out_dir}"
    )


def cmd_table(args: argparse.Namespace) -> None:
    from diacc.experiments.report import build_table, expand_rows, render_table

    rows = expand_rows(args.rows)
    if args.out:
        check_output_file(args.out)  # before reading every results file
    table = build_table(args.results, args.speed_std, rows, args.paired_against)
    text = render_table(table, args.format)
    if args.out:
        try:
            args.out.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputPathError(f"cannot write {args.out} ({exc.strerror})") from None
        atomic_write(args.out, text)
        print(f"table written to {args.out}")
    else:
        sys.stdout.write(text)


def cmd_plot(args: argparse.Namespace) -> None:
    from diacc.experiments import plots

    if args.plot_kind == "curves":
        paths = plots.plot_curves(args.runs, args.out, smooth=args.smooth)
    elif args.plot_kind == "timespace":
        from diacc.experiments.policies import parse_policy
        from diacc.experiments.timespace import plot_timespace

        spec = parse_policy(args.policy, args.variant, args.actions == "sampled")
        cell = _episode_cell(args)
        paths = plot_timespace(spec, cell, args.out, None, _settings(args), seed=args.seed)
    elif args.plot_kind == "flow":
        from diacc.experiments.flowplot import plot_flow

        paths, _ = plot_flow(args.results, args.out)
    else:
        paths = plots.plot_speeds(args.results, args.out, map_name=args.map)
    print("wrote " + ", ".join(map(str, paths)))


def cmd_render(args: argparse.Namespace) -> None:
    from diacc.experiments.policies import parse_policy
    from diacc.experiments.render import render_episode

    spec = parse_policy(args.policy, args.variant, args.actions == "sampled")
    cell = _episode_cell(args)
    result = render_episode(
        spec,
        cell,
        args.out,
        None,  # as long as the episode: --episode-steps, else the policy's own
        _settings(args),
        seed=args.seed,
        fps=args.fps,
        view=args.view,
    )
    print(
        f"wrote {result.path}: {result.n_frames} frames, PSAR highlighted in {result.psar_frames}"
    )


def cmd_scorecard(args: argparse.Namespace) -> None:
    from diacc.experiments.policies import parse_policy
    from diacc.experiments.scorecard import (
        DEFAULT_AGENT,
        SCORECARD_JSON,
        SCORECARD_MD,
        SUITES,
        ScorecardConfig,
        run_scorecard,
    )

    backends = tuple(options.csv_list(args.backends))
    unknown = [b for b in backends if b not in BACKENDS]
    if unknown or not backends:
        raise ConfigError(f"unknown backend {(unknown or [''])[0]!r}; use {', '.join(BACKENDS)}")
    cfg = ScorecardConfig(
        policy=tuple(parse_policy(p, sampled=args.actions == "sampled") for p in args.policy),
        out_dir=args.out,
        episodes=args.episodes,
        suites=tuple(SUITES) if args.suites == "all" else tuple(options.csv_list(args.suites)),
        backends=backends,
        agent=args.agent or DEFAULT_AGENT,
        episode_steps=args.episode_steps,
        stream=args.stream,
        workers=args.workers,
    )
    run_scorecard(cfg, say=lambda line: print(line, flush=True))
    print(f"scorecard: {args.out / SCORECARD_MD} and {args.out / SCORECARD_JSON}")


COMMANDS = {
    "eval": cmd_eval,
    "table": cmd_table,
    "plot": cmd_plot,
    "render": cmd_render,
    "scorecard": cmd_scorecard,
}
