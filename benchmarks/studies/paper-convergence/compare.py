"""Each learned column's delay against same-mix, the heuristic and each other: pooled and
per seed.

    python benchmarks/studies/paper-convergence/compare.py RESULTS_DIR \
        [--metric delay] [--against COLUMN ...]

``RESULTS_DIR`` is a ``diacc reproduce`` output (``results/paper-congestion``, or a
study's ``results/paper-congestion-study-tau``). A learned column is a variant, or a
variant and its study setting (``diacc-tau_init2-tau_final0.05``), pooling its seeds.
For every backend and evaluated cell it prints one Markdown table: each learned column's
change of the mean of ``--metric`` (a table row key) against ``same-mix``, ``heuristic``
and the ``--against`` columns (default: the ``mappo-iadm`` column of each map, ``—`` on
the other map's cells; a baseline such as ``pure-hdv`` too), with the 95 % paired
bootstrap interval (seeds pooled, seeds and episodes resampled:
``diacc/experiments/paired.py``), then the change against same-mix of each seed alone,
and the share of episodes that end in a collision (where it is 100 %, the episodes end
early and their delay means nothing). First, each run's training delay per vehicle over
its last ``--last-steps`` env steps (sampled actions, from ``runs/*/progress.jsonl``).
The numbers of docs/results/paper-convergence.md come from it.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from diacc.errors import DiaccError
from diacc.experiments.plots import read_progress
from diacc.experiments.report import TRAINING_RUN, table_from_results
from diacc.experiments.results_files import load_episodes

RUN = re.compile(r"^(?P<variant>[a-z-]+)-(?P<map>train-\d+)-s(?P<seed>\d+)(?:-(?P<setting>.+))?$")
BASELINES = ("pure-hdv", "same-mix", "cooperative", "heuristic")
#: The study's training map: its runs' columns carry no map name, others' do.
MAIN_MAP = "train-50"


def column_name(match: re.Match) -> str:
    """A run's learned column: its variant and study setting, and its map where that is
    not the study's main one (the runs of both reductions are different columns)."""
    column = "-".join(filter(None, (match["variant"], match["setting"])))
    return column if match["map"] == MAIN_MAP else f"{column}@{match['map']}"


def columns(eval_dir: Path) -> tuple[list, dict[str, list[str]]]:
    """(loaded columns, learned column -> its seeds): baselines, then each learned column
    pooling its seeds (rows tagged with their ``TRAINING_RUN``), then each seed alone."""
    loaded, pooled, seeds = [], {}, {}
    for name in BASELINES:
        loaded.append((Path(name), *load_episodes(eval_dir / name)))
    for run_dir in sorted(p for p in eval_dir.iterdir() if RUN.match(p.name)):
        match = RUN.match(run_dir.name)
        meta, rows = load_episodes(run_dir)
        variant = column_name(match)
        seed = match["seed"]
        seeds.setdefault(variant, []).append(seed)
        run = len(seeds[variant]) - 1
        tagged = [dict(r, **{TRAINING_RUN: run}) for r in rows]
        if variant in pooled:
            pooled[variant][2].extend(tagged)
        else:
            pooled[variant] = (Path(variant), dict(meta, policy=variant), tagged)
        loaded.append((Path(f"{variant}-s{seed}"), dict(meta, policy=f"{variant} s{seed}"), rows))
    return loaded[: len(BASELINES)] + list(pooled.values()) + loaded[len(BASELINES) :], seeds


def training_delays(runs_dir: Path, last_steps: int) -> dict[str, list[str]]:
    """Learned column -> "s<seed> <mean training delay per vehicle over the run's last
    ``last_steps`` env steps> @ <steps reached>" per seed (sampled actions,
    ``progress.jsonl``)."""
    delays: dict[str, list[str]] = {}
    for run_dir in sorted(p for p in runs_dir.iterdir() if RUN.match(p.name)):
        match = RUN.match(run_dir.name)
        series = read_progress(run_dir).get("episode/delay_per_vehicle_s")
        if series is None:
            continue
        steps, delay = series  # (T,), (T,)
        last = delay[steps > steps.max() - last_steps]
        column = column_name(match)
        reached = f"{steps.max() / 1000:,.0f}k"  # a run still training shows how far it is
        delays.setdefault(column, []).append(f"s{match['seed']} {last.mean():.1f} @ {reached}")
    return delays


def interval(change, unit: str = "") -> str:
    """``-12.3 [-15.0, -9.1]``, marked ``≈`` where the interval holds 0; "—" for none."""
    if change is None:
        return "—"
    mark = "" if change.measurable else "≈ "
    low, point, high = (round(x, 1) + 0.0 for x in (change.low, change.change, change.high))
    return f"{mark}{point:+.1f}{unit} [{low:+.1f}, {high:+.1f}]"  # + 0.0: no "-0.0"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("results_dir", type=Path)
    parser.add_argument("--metric", default="delay")
    parser.add_argument("--against", action="append", default=None)
    parser.add_argument("--last-steps", type=int, default=50_000)
    args = parser.parse_args()
    metric = args.metric
    if not any((args.results_dir / d).is_dir() for d in ("eval", "runs")):
        parser.error(f"{args.results_dir}: no runs/ or eval/ (not a diacc reproduce output)")
    if (args.results_dir / "runs").is_dir():
        print(
            f"## training: delay per vehicle (s) over each run's last {args.last_steps:,} steps\n"
        )
        for column, entries in training_delays(args.results_dir / "runs", args.last_steps).items():
            print(f"- {column}: {', '.join(entries)}")
        print()
    evaluated = args.results_dir / "eval"  # absent while the runs still train
    for backend_dir in sorted(evaluated.iterdir()) if evaluated.is_dir() else []:
        loaded, seeds = columns(backend_dir)
        table = table_from_results(loaded, rows=(metric, "collision"))
        others = args.against or [c for c in seeds if c.split("@")[0] == "mappo-iadm"]
        unknown = [c for c in others if c not in seeds and c not in BASELINES]
        if unknown:
            parser.error(f"--against {unknown[0]}: not a learned column or baseline here")
        against = list(dict.fromkeys(["same-mix", "heuristic", *others]))
        print(f"## {backend_dir.name}: {metric}, change of the mean in % (pp for shares)\n")
        for cell in sorted(table.cells, key=lambda c: not c.map.startswith("train")):
            print(f"**{cell.key}**\n")
            heads = [f"vs {a}" for a in against] + ["vs same-mix, per seed", "collision episodes"]
            print("| column | " + " | ".join(heads) + " |")
            print("|---" * (len(heads) + 1) + "|")
            for variant, its_seeds in seeds.items():
                if (cell.key, "collision", variant) not in table.stats:
                    continue  # a run of the other map's column, not played here
                entries = []
                for other in against:
                    if (cell.key, "collision", other) not in table.stats:
                        entries.append("—")  # the other map's column: it never played here
                        continue
                    table.paired_against = other
                    entries.append(interval(table.paired(cell, metric, variant)))
                table.paired_against = "same-mix"
                per_seed = [table.paired(cell, metric, f"{variant} s{s}") for s in its_seeds]
                entries.append(
                    ", ".join(
                        f"s{s} {interval(c)}" for s, c in zip(its_seeds, per_seed, strict=True)
                    )
                )
                collided = table.stats[(cell.key, "collision", variant)]
                entries.append(f"{collided.mean:.0f} % of {collided.n_episodes}")
                print(f"| {variant} | " + " | ".join(entries) + " |")
            print()


if __name__ == "__main__":
    try:
        main()
    except DiaccError as error:  # a missing or malformed results file: one line
        raise SystemExit(f"compare.py: error: {error}") from None
