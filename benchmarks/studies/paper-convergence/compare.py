"""The variants' delay against same-mix, each other and the heuristic: pooled and per seed.

    python benchmarks/studies/paper-convergence/compare.py RESULTS_DIR [METRIC]

``RESULTS_DIR`` is a ``diacc reproduce`` output (``results/paper-congestion``);
``METRIC`` a table row key (default ``delay``). For every backend and evaluated
cell it prints one Markdown table: each learned variant's change of the mean
against ``same-mix``, ``heuristic`` and ``mappo-iadm``, with the 95 % paired
bootstrap interval (the reproduction's seeds pooled, seeds and episodes
resampled: ``diacc/experiments/paired.py``), then the change against same-mix of
each seed alone, and the share of episodes that end in a collision (where
it is 100 %, the episodes end early and their delay means nothing). The numbers
of docs/results/paper-convergence.md come from it.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

from diacc.experiments.report import table_from_results
from diacc.experiments.results_files import load_episodes

RUN = re.compile(r"^(?P<variant>[a-z-]+)-train-\d+-s(?P<seed>\d+)$")
BASELINES = ("pure-hdv", "same-mix", "cooperative", "heuristic")
AGAINST = ("same-mix", "heuristic", "mappo-iadm")


def columns(eval_dir: Path) -> tuple[list, dict[str, list[str]]]:
    """(loaded columns, variant -> its seeds): baselines, then each variant pooling its
    seeds (rows tagged with their ``training_run``), then each seed alone."""
    loaded, pooled, seeds = [], {}, {}
    for name in BASELINES:
        loaded.append((Path(name), *load_episodes(eval_dir / name)))
    for run_dir in sorted(p for p in eval_dir.iterdir() if RUN.match(p.name)):
        match = RUN.match(run_dir.name)
        meta, rows = load_episodes(run_dir)
        variant, seed = match["variant"], match["seed"]
        seeds.setdefault(variant, []).append(seed)
        run = len(seeds[variant]) - 1
        tagged = [dict(r, training_run=run) for r in rows]
        if variant in pooled:
            pooled[variant][2].extend(tagged)
        else:
            pooled[variant] = (Path(variant), dict(meta, policy=variant), tagged)
        loaded.append((Path(f"{variant}-s{seed}"), dict(meta, policy=f"{variant} s{seed}"), rows))
    return loaded[: len(BASELINES)] + list(pooled.values()) + loaded[len(BASELINES) :], seeds


def interval(change) -> str:
    if change is None:
        return "—"
    mark = "" if change.measurable else "≈ "
    return f"{mark}{change.change:+.1f} [{change.low:+.1f}, {change.high:+.1f}]"


def main() -> None:
    out = Path(sys.argv[1])
    metric = sys.argv[2] if len(sys.argv) > 2 else "delay"
    for backend_dir in sorted((out / "eval").iterdir()):
        loaded, seeds = columns(backend_dir)
        table = table_from_results(loaded, rows=(metric, "collision"))
        print(f"## {backend_dir.name}: {metric}, change of the mean in % (pp for shares)\n")
        for cell in sorted(table.cells, key=lambda c: not c.map.startswith("train")):
            print(f"**{cell.key}**\n")
            heads = [f"vs {a}" for a in AGAINST] + ["vs same-mix, per seed", "collision episodes"]
            print("| variant | " + " | ".join(heads) + " |")
            print("|---" * (len(heads) + 1) + "|")
            for variant, its_seeds in seeds.items():
                entries = []
                for against in AGAINST:
                    table.paired_against = against
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
    main()
