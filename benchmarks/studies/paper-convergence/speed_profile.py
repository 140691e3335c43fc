"""The paper's speed-distribution claim in numbers: per segment kind, each column's median
speed, interquartile range and share of low-speed samples on the dense zero-shot rows, and
one learned column against every other one, paired by episode.

    python benchmarks/studies/paper-convergence/speed_profile.py RESULTS_DIR \
        [--vehicles 30,40] [--low-mps 5] [--column diacc]

The paper's figure "Speed distribution comparison" (box plots and KDEs at N = 30 and 40)
says DIACC "achieves the highest median speed among all methods" with "the smallest
[proportion] in low-speed regions"; it gives no number. ``diacc plot speeds`` draws the
panels; this prints what they show. ``RESULTS_DIR`` is a ``diacc reproduce`` output whose
evaluation still holds its speed samples (``eval/<backend>/<column>/speeds.csv.gz``: they
are not committed, so run it where the evaluation ran). Learned columns pool their seeds
as in ``compare.py``.

Per cell (``--vehicles`` picks the rows by vehicle count) and segment kind:

* the level: median and interquartile range of all the column's samples (what a box plot
  draws), and the share of samples below ``--low-mps``;
* ``--column``'s change against each other column over the episodes both played (the same
  traffic), with the 95 % bootstrap interval of ``diacc/experiments/paired.py``: the mean
  of the per-episode medians in %, the low-speed share in percentage points (weighted by
  the episode's samples, so it is the pooled share).
"""

from __future__ import annotations

import argparse
import csv
import gzip
from collections import defaultdict
from pathlib import Path

import numpy as np
from compare import BASELINES, RUN, column_name, interval  # beside this script

from diacc.errors import DiaccError
from diacc.experiments.grid import Cell
from diacc.experiments.paired import EpisodeValues, paired_change
from diacc.experiments.results_files import SPEEDS_FILE
from diacc.sim.maps import SEGMENT_KINDS

# (cell key, segment kind) -> (episode, run) -> speed samples (S,)
Samples = dict[tuple[str, str], dict[tuple[int, int], np.ndarray]]


def cell_key(row: dict) -> str:
    """The key of a speed sample's cell (``test-50_N30_rho0.30_D1``)."""
    return Cell(
        row["map"], int(row["n_vehicles"]), float(row["cav_penetration"]), row["style_mix"]
    ).key


def read_samples(result_dir: Path, vehicles: set[int], run: int, into: Samples) -> None:
    """Add the speed samples of one results directory's cells with ``vehicles`` vehicles."""
    path = result_dir / SPEEDS_FILE
    if not path.is_file():
        raise DiaccError(f"{result_dir} has no {SPEEDS_FILE} (speed samples are not committed)")
    lists: dict = defaultdict(list)
    with gzip.open(path, "rt", newline="") as f:
        for row in csv.DictReader(f):
            if int(row["n_vehicles"]) in vehicles:
                key = (cell_key(row), row["segment_kind"])
                lists[key, (int(row["episode"]), run)].append(float(row["speed_mps"]))
    for (key, episode_run), speeds in lists.items():
        into.setdefault(key, {})[episode_run] = np.asarray(speeds)  # (S,)


def load_columns(backend_dir: Path, vehicles: set[int]) -> dict[str, Samples]:
    """Column -> its samples: the baselines, then each learned column pooling its seeds."""
    found: dict[str, Samples] = {}
    for name in BASELINES:
        if (backend_dir / name).is_dir():
            read_samples(backend_dir / name, vehicles, 0, found.setdefault(name, {}))
    runs: dict[str, int] = defaultdict(int)
    for run_dir in sorted(p for p in backend_dir.iterdir() if RUN.match(p.name)):
        column = column_name(RUN.match(run_dir.name))
        read_samples(run_dir, vehicles, runs[column], found.setdefault(column, {}))
        runs[column] += 1
    return found


def per_episode(samples: dict[tuple[int, int], np.ndarray], low_mps: float):
    """(median per episode, low-speed share per episode in %) as EpisodeValues."""
    keys = sorted(samples)
    seed = np.array([e for e, _ in keys], np.int64)  # (K,) episode number: the same traffic
    run = np.array([r for _, r in keys], np.int64)  # (K,)
    counts = np.array([samples[k].size for k in keys], float)  # (K,)
    medians = np.array([np.median(samples[k]) for k in keys])  # (K,)
    low = np.array([100.0 * np.mean(samples[k] < low_mps) for k in keys])  # (K,)
    return (
        EpisodeValues(seed, medians, np.ones_like(counts), run),
        EpisodeValues(seed, low, counts, run),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("results_dir", type=Path)
    parser.add_argument("--vehicles", default="30,40", help="vehicle counts of the rows")
    parser.add_argument("--low-mps", type=float, default=5.0, help="low-speed threshold")
    parser.add_argument("--column", default="diacc", help="the column compared with the others")
    args = parser.parse_args()
    vehicles = {int(v) for v in args.vehicles.split(",")}
    evaluated = args.results_dir / "eval"
    if not evaluated.is_dir():
        parser.error(f"{args.results_dir}: no eval/ (not an evaluated diacc reproduce output)")
    for backend_dir in sorted(evaluated.iterdir()):
        columns = load_columns(backend_dir, vehicles)
        if args.column not in columns:
            parser.error(f"--column {args.column}: not a column of {backend_dir}")
        mine = columns[args.column]
        low = f"low speed < {args.low_mps:g} m/s"
        print(f"## {backend_dir.name}: {args.column} against each column, {low}\n")
        for key in sorted({k for k, _ in mine}):
            print(f"**{key}**\n")
            print(
                "| column | segment | median (IQR), m/s | low-speed share | "
                f"{args.column}: median change | {args.column}: low-speed change |"
            )
            print("|---|---|---|---|---|---|")
            for name, samples in columns.items():
                for kind in SEGMENT_KINDS:
                    theirs = samples.get((key, kind))
                    if not theirs:
                        continue
                    pooled = np.concatenate(list(theirs.values()))  # (S,)
                    q1, q2, q3 = np.percentile(pooled, [25, 50, 75])
                    level = f"{q2:.1f} ({q1:.1f}-{q3:.1f})"
                    share = f"{100.0 * np.mean(pooled < args.low_mps):.1f} %"
                    changes = ["", ""]
                    if name != args.column and (key, kind) in mine:
                        ours = per_episode(mine[key, kind], args.low_mps)
                        ref = per_episode(theirs, args.low_mps)
                        changes = [
                            interval(paired_change(ours[0], ref[0], relative=True), " %"),
                            interval(paired_change(ours[1], ref[1], relative=False), " pp"),
                        ]
                    print(f"| {name} | {kind} | {level} | {share} | " + " | ".join(changes) + " |")
            print()


if __name__ == "__main__":
    try:
        main()
    except DiaccError as error:  # a missing or malformed results file: one line
        raise SystemExit(f"speed_profile.py: error: {error}") from None
