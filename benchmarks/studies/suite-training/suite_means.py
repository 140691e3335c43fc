"""Mean delay over a whole suite of a scorecard, each seed against each reference.

    python benchmarks/studies/suite-training/suite_means.py CARD_DIR SUITE [BACKEND]
        [--against NAME ...] [--candidates NAME ...]

Pairs every candidate episode with the reference's episode of the same cell and seed,
and prints the relative change of the suite's mean delay per vehicle with a 95 %
paired bootstrap interval (2,000 resamples of the pairs, seeded): issue 60's
"generated suite: delay against the heuristic better with the interval excluding 0".
With several seeds a last line per reference pools them (the recipe, no seed chosen).
``--against`` adds result folders of the card as references (``suite-s3``, the shipped
suite agent copied into the fine-tuned agents' test card; ``policy-1``, a candidate);
``--candidates`` scores those folders only (one arm's seeds, pooled).
"""

from __future__ import annotations

import argparse
import csv
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


def change_line(label: str, name: str, pairs: list[tuple[float, float]], rng) -> str:
    """The relative change of the mean delay over ``pairs`` (candidate, reference)."""
    a = np.array([p[0] for p in pairs])  # (P,)
    b = np.array([p[1] for p in pairs])  # (P,)
    picks = rng.integers(0, len(pairs), (2000, len(pairs)))  # (R, P)
    change = (a[picks].mean(1) / b[picks].mean(1) - 1) * 100  # (R,)
    low, high = np.percentile(change, [2.5, 97.5])
    return (
        f"{label} vs {name}: {a.mean():.2f} vs {b.mean():.2f} s, "
        f"{(a.mean() / b.mean() - 1) * 100:+.1f} % [{low:+.1f}, {high:+.1f}], "
        f"{len(pairs)} pairs"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("card", type=Path)
    parser.add_argument("suite")
    parser.add_argument("backend", nargs="?", default="highway")
    parser.add_argument("--against", nargs="+", default=[], metavar="NAME")
    parser.add_argument("--candidates", nargs="+", metavar="NAME")
    args = parser.parse_args()
    where = args.card / args.backend / args.suite
    if not where.is_dir():
        parser.error(f"no results of suite {args.suite!r} on {args.backend} in {args.card}")
    names = (*REFERENCES, *args.against)
    refs = {name: delays(where / name) for name in names if (where / name).exists()}
    rng = np.random.default_rng(0)
    candidates = args.candidates or sorted(
        p.name for p in where.iterdir() if p.name.startswith("policy")
    )
    pooled: dict[str, list[tuple[float, float]]] = {name: [] for name in refs}
    for cand in candidates:
        mine = delays(where / cand)
        for name, ref in refs.items():
            if name == cand:
                continue
            pairs = [(mine[k], ref[k]) for k in sorted(set(mine) & set(ref))]
            pooled[name] += pairs
            print(change_line(f"{args.suite} {cand}", name, pairs, rng))
    if len(candidates) > 1:  # the recipe: every seed's episodes, each paired with its reference
        for name, pairs in pooled.items():
            if pairs:
                print(
                    change_line(f"{args.suite} pooled ({len(candidates)} seeds)", name, pairs, rng)
                )


if __name__ == "__main__":
    main()
