"""Command-line parsers and handlers for ``diacc eval | table | plot | render``.

Registered by :mod:`diacc.cli` (``add_parsers`` and ``COMMANDS``); errors are
the one-line exceptions of the modules they call.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from diacc.config import BACKENDS, STYLE_PRESETS


def _settings(args: argparse.Namespace):
    from diacc.policies import EvalSettings

    return EvalSettings(
        backend=args.backend, episode_steps=args.episode_steps, style_preset=args.style_preset
    )


def _policy_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--policy",
        required=True,
        help="pure-hdv, cooperative, or a checkpoint.pt (or its run directory)",
    )
    p.add_argument("--variant", default=None, help="require the checkpoint to be of this variant")
    p.add_argument("--backend", choices=BACKENDS, default="highway")
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


def add_parsers(sub) -> None:
    """Add the evaluation subcommands to the main parser."""
    p = sub.add_parser("eval", help="evaluate a policy or baseline on a grid of scenarios")
    _policy_args(p)
    p.add_argument("--grid", default="train", help="train, zero-shot, or a grid .toml file")
    p.add_argument("--episodes", type=int, default=10, help="seeded episodes per cell")
    p.add_argument("--out", required=True, type=Path, help="results directory")
    p.add_argument("--workers", type=int, default=1, help="worker processes (spawn)")
    p.add_argument("--no-progress", action="store_true")

    p = sub.add_parser("table", help="paper-style table (Tables II/III) from results directories")
    p.add_argument("results", nargs="+", type=Path, help="results directories, one per column")
    p.add_argument("--format", choices=("markdown", "latex", "csv"), default="markdown")
    p.add_argument(
        "--speed-std",
        choices=("samples", "episodes"),
        default="samples",
        help="speed std over all vehicle-steps (paper) or over episode means",
    )
    p.add_argument("--out", type=Path, default=None, help="write to a file instead of stdout")

    p = sub.add_parser("plot", help="training curves or speed distributions (PNG + PDF)")
    plot_sub = p.add_subparsers(dest="plot_kind", required=True)
    q = plot_sub.add_parser("curves", help="collision rate, global and individual reward")
    q.add_argument("runs", nargs="+", type=Path, help="run directories (seeds of a variant group)")
    q.add_argument("--out", type=Path, default=Path("figures/curves"))
    q.add_argument("--smooth", type=int, default=1, help="moving-average window (updates)")
    q = plot_sub.add_parser("speeds", help="per-segment speed box plots and KDEs")
    q.add_argument("results", nargs="+", type=Path, help="results directories")
    q.add_argument("--out", type=Path, default=Path("figures/speeds"))
    q.add_argument("--map", default=None, help="only the samples of this map")

    p = sub.add_parser("render", help="one episode as a GIF")
    _policy_args(p)
    p.add_argument("--map", default="train-25")
    p.add_argument("--vehicles", type=int, default=25)
    p.add_argument("--penetration", type=float, default=0.4)
    p.add_argument("--mix", default="D1")
    p.add_argument("--steps", type=int, default=100, help="decisions to render at most")
    p.add_argument("--seed", type=int, default=None, help="default: seed of eval episode 0")
    p.add_argument("--fps", type=float, default=5.0)
    p.add_argument("--out", type=Path, default=Path("episode.gif"))


def cmd_eval(args: argparse.Namespace) -> None:
    from diacc.evaluate import evaluate
    from diacc.grid import load_grid
    from diacc.policies import parse_policy

    spec = parse_policy(args.policy, args.variant)
    cells = load_grid(args.grid)
    summary = evaluate(
        spec,
        cells,
        args.episodes,
        args.out,
        _settings(args),
        workers=args.workers,
        progress=not args.no_progress,
    )
    print(
        f"{len(summary.cells_run)} cells run, {len(summary.cells_skipped)} already done; "
        f"results in {summary.out_dir}"
    )


def cmd_table(args: argparse.Namespace) -> None:
    from diacc.report import build_table, render_table

    text = render_table(build_table(args.results, args.speed_std), args.format)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
        print(f"table written to {args.out}")
    else:
        sys.stdout.write(text)


def cmd_plot(args: argparse.Namespace) -> None:
    from diacc import plots

    if args.plot_kind == "curves":
        paths = plots.plot_curves(args.runs, args.out, smooth=args.smooth)
    else:
        paths = plots.plot_speeds(args.results, args.out, map_name=args.map)
    print("wrote " + ", ".join(map(str, paths)))


def cmd_render(args: argparse.Namespace) -> None:
    from diacc.grid import make_cell
    from diacc.policies import parse_policy
    from diacc.render import render_episode

    spec = parse_policy(args.policy, args.variant)
    cell = make_cell(
        {
            "map": args.map,
            "n_vehicles": args.vehicles,
            "cav_penetration": args.penetration,
            "style_mix": args.mix,
        },
        "render",
    )
    result = render_episode(
        spec, cell, args.out, args.steps, _settings(args), seed=args.seed, fps=args.fps
    )
    print(
        f"wrote {result.path}: {result.n_frames} frames, PSAR highlighted in {result.psar_frames}"
    )


COMMANDS = {"eval": cmd_eval, "table": cmd_table, "plot": cmd_plot, "render": cmd_render}
