"""One row per evaluated run of the no-PSAR study: collisions, arrivals, delay.

    python benchmarks/studies/nopsar-learning/summarise.py [--stream validation] [--paired]

Reads ``results/<arm>/eval/<stream>-<backend>/<run>/episodes.csv`` (``eval.sh``)
and prints a markdown table: per run and simulator, the share of episodes
with a collision (95 % Wilson interval), vehicles in a collision per episode,
the share of vehicles that arrived and the delay per vehicle (mean over
episodes). Every run is listed, none left out.
"""

from __future__ import annotations

import argparse
import csv
import math
from pathlib import Path

HERE = Path(__file__).resolve().parent


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of a share k / n."""
    if n == 0:
        return math.nan, math.nan
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def mean(values: list[float]) -> float:
    values = [v for v in values if not math.isnan(v)]
    return sum(values) / len(values) if values else math.nan


def delays_by_episode(csv_path: Path) -> dict[tuple[str, ...], float]:
    """Delay per vehicle keyed by (cell, episode seed): a grid of several cells (the dense
    rows) plays the same episode seeds in each."""
    with csv_path.open() as fh:
        return {
            tuple(r[k] for k in ("map", "n_vehicles", "cav_penetration", "seed")): float(
                r["delay_per_vehicle_s"]
            )
            for r in csv.DictReader(fh)
        }


def paired(results: Path, stream: str) -> None:
    """Delay change against the references on the same episodes; collisions pooled over
    the seeds of each arm and variant (a run folder is ``<variant>-s<seed>``)."""
    print("\n| arm | run | simulator | episodes | delay vs same-mix [s, 95 % CI] | vs heuristic |")
    print("|---|---|---|---|---|---|")
    pooled: dict[tuple[str, str, str], list[int]] = {}
    for csv_path in sorted(results.glob(f"*/eval/{stream}-*/*/episodes.csv")):
        arm, folder = csv_path.parents[3].name, csv_path.parent.parent.name
        if arm == "reference":
            continue
        mine = delays_by_episode(csv_path)
        cells = []
        for ref in ("same-mix", "heuristic"):
            # the references evaluated under the same suffix (-30ep), else the plain folder
            # (the same seeds: a stream's episode i has one seed)
            ref_csv = results / "reference" / "eval" / folder / ref / "episodes.csv"
            if not ref_csv.is_file():
                plain = "-".join(folder.split("-")[:2])
                ref_csv = results / "reference" / "eval" / plain / ref / "episodes.csv"
            if not ref_csv.is_file():
                cells.append("(not evaluated)")
                continue
            theirs = delays_by_episode(ref_csv)
            diffs = [mine[s] - theirs[s] for s in mine if s in theirs]
            if len(diffs) < 2:
                cells.append("(no shared episodes)")
                continue
            m = sum(diffs) / len(diffs)
            sd = math.sqrt(sum((d - m) ** 2 for d in diffs) / (len(diffs) - 1))
            half = 1.96 * sd / math.sqrt(len(diffs))
            cells.append(f"{m:+.2f} [{m - half:+.2f}, {m + half:+.2f}]")
        backend = folder.split("-", 1)[1]
        run = csv_path.parent.name
        print(f"| {arm} | {run} | {backend} | {len(mine)} | {cells[0]} | {cells[1]} |")
        with csv_path.open() as fh:
            rows = list(csv.DictReader(fh))
        variant = run.rsplit("-s", 1)[0]
        count = pooled.setdefault((arm, variant, backend), [0, 0])
        count[0] += sum(int(float(r["collision"])) > 0 for r in rows)
        count[1] += len(rows)
    print("\n| arm | variant | simulator | episodes with a collision, pooled [95 % CI] |")
    print("|---|---|---|---|")
    for (arm, variant, backend), (k, n) in pooled.items():
        lo, hi = wilson(k, n)
        share = f"{k} / {n} = {k / n:.1%} [{lo:.1%}, {hi:.1%}]"
        print(f"| {arm} | {variant} | {backend} | {share} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stream", default="validation")
    parser.add_argument("--results", type=Path, default=HERE / "results")
    parser.add_argument("--paired", action="store_true", help="delay changes, pooled shares")
    args = parser.parse_args()
    print(
        "| arm | run | simulator | episodes | with a collision [95 % CI] | "
        "collided vehicles / episode | arrived | delay / vehicle [s] |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for csv_path in sorted(args.results.glob(f"*/eval/{args.stream}-*/*/episodes.csv")):
        run, stream_backend, arm = csv_path.parent.name, csv_path.parent.parent.name, None
        arm = csv_path.parents[3].name
        backend = stream_backend.split("-", 1)[1]
        with csv_path.open() as fh:
            rows = list(csv.DictReader(fh))
        n = len(rows)
        k = sum(int(float(r["collision"])) > 0 for r in rows)
        lo, hi = wilson(k, n)
        crashes = mean([float(r["n_collisions"]) for r in rows])
        arrived = mean([float(r["arrived_fraction"]) for r in rows])
        delay = mean([float(r["delay_per_vehicle_s"]) for r in rows])
        print(
            f"| {arm} | {run} | {backend} | {n} | {k / n:.0%} [{lo:.0%}, {hi:.0%}] | "
            f"{crashes:.1f} | {arrived:.2f} | {delay:.1f} |"
        )
    if args.paired:
        paired(args.results, args.stream)


if __name__ == "__main__":
    main()
