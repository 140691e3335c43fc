"""Mean delay over a whole suite of a scorecard, each seed against each reference.

    python benchmarks/studies/suite-training/suite_means.py CARD_DIR SUITE [BACKEND]

Pairs every candidate episode with the reference's episode of the same cell and seed,
and prints the relative change of the suite's mean delay per vehicle with a 95 %
paired bootstrap interval (2,000 resamples of the pairs, seeded): issue 60's
"generated suite: delay against the heuristic better with the interval excluding 0".
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import numpy as np

REFERENCES = ("same-mix", "heuristic", "diacc")
#: What identifies one episode of a suite: its cell and its episode number.
KEY = ("map", "n_vehicles", "cav_penetration", "style_mix", "inflow_vph", "episode")


def delays(results: Path) -> dict[tuple[str, ...], float]:
    with (results / "episodes.csv").open() as f:
        return {
            tuple(r[k] for k in KEY): float(r["delay_per_vehicle_s"]) for r in csv.DictReader(f)
        }


def main() -> None:
    card, suite = Path(sys.argv[1]), sys.argv[2]
    where = card / (sys.argv[3] if len(sys.argv) > 3 else "highway") / suite
    refs = {name: delays(where / name) for name in REFERENCES if (where / name).exists()}
    rng = np.random.default_rng(0)
    for cand in sorted(p.name for p in where.iterdir() if p.name.startswith("policy")):
        mine = delays(where / cand)
        for name, ref in refs.items():
            keys = sorted(set(mine) & set(ref))
            a = np.array([mine[k] for k in keys])  # (P,)
            b = np.array([ref[k] for k in keys])  # (P,)
            picks = rng.integers(0, len(keys), (2000, len(keys)))  # (R, P)
            change = (a[picks].mean(1) / b[picks].mean(1) - 1) * 100  # (R,)
            low, high = np.percentile(change, [2.5, 97.5])
            print(
                f"{suite} {cand} vs {name}: {a.mean():.2f} vs {b.mean():.2f} s, "
                f"{(a.mean() / b.mean() - 1) * 100:+.1f} % [{low:+.1f}, {high:+.1f}], "
                f"{len(keys)} pairs"
            )


if __name__ == "__main__":
    main()
