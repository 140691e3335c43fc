"""One row per evaluated run of the no-PSAR study: collisions, arrivals, delay.

    python benchmarks/studies/nopsar-learning/summarise.py [--stream validation]

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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stream", default="validation")
    parser.add_argument("--results", type=Path, default=HERE / "results")
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


if __name__ == "__main__":
    main()
