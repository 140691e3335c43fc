"""diacc-nopsar against mappo on the paper's dense zero-shot rows (issue 60, item 4).

    python benchmarks/studies/nopsar-learning/dense_rows.py [--arm ARM] > results/ARM/dense-rows.md
    python benchmarks/studies/nopsar-learning/dense_rows.py --at 30ep   # the training cell

Reads the `test` evaluations that ``eval.sh`` writes with ``AT=dense
GRID=benchmarks/studies/paper-convergence/dense-rows.toml`` (``results/<arm>/eval/
test-<backend>-dense/<variant>-s<seed>/`` and the references' under
``results/reference/``) and prints, per row and simulator, every seed's episodes with
a collision and delay against same-mix and the heuristic, then the two variants
pooled over their seeds against each other. The paper's Table IV puts DIACC 17-20 %
ahead of MAPPO-IADM in speed on these rows; here the pair that differs in both
networks (TAIE + GRU actor and ITDR critic against MLPs) is the one the no-PSAR
recipe trained. Intervals: 95 % paired bootstrap that resamples episodes and, for a
pooled variant, its seeds too (2,000 resamples, seeded). Every seed is listed.
"""

from __future__ import annotations

import argparse
import csv
from collections import defaultdict
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
#: What names one row of the grid (the episode number runs within it).
ROW = ("map", "n_vehicles", "cav_penetration", "style_mix")
RESAMPLES = 2000


Episode = tuple[float, float, bool]  # delay per vehicle [s], mean speed [m/s], a collision


def read(folder: Path) -> dict[tuple[str, ...], dict[int, Episode]]:
    """{row: {episode: (delay, speed, had a collision)}} of one evaluation."""
    rows: dict[tuple[str, ...], dict[int, Episode]] = defaultdict(dict)
    with (folder / "episodes.csv").open() as fh:
        for r in csv.DictReader(fh):
            rows[tuple(r[k] for k in ROW)][int(r["episode"])] = (
                float(r["delay_per_vehicle_s"]),
                float(r["mean_speed_mps"]),
                r["collision"] == "1",
            )
    return rows


def change(mine: np.ndarray, theirs: np.ndarray, relative: bool = False) -> str:
    """Mean change of ``mine`` (S, P) over ``theirs`` (S', P), paired by episode P (in %
    of theirs if ``relative``); the bootstrap resamples the episodes and each side's
    seeds S, seeded per comparison (an interval does not depend on the runs beside it)."""
    rng = np.random.default_rng(0)
    s_mine, s_theirs, pairs = mine.shape[0], theirs.shape[0], mine.shape[1]
    episodes = rng.integers(0, pairs, (RESAMPLES, pairs))  # (R, P)
    seeds_mine = rng.integers(0, s_mine, (RESAMPLES, s_mine))  # (R, S)
    seeds_theirs = rng.integers(0, s_theirs, (RESAMPLES, s_theirs))  # (R, S')
    diffs = np.empty(RESAMPLES)
    for i in range(RESAMPLES):
        a = mine[seeds_mine[i]][:, episodes[i]].mean()
        b = theirs[seeds_theirs[i]][:, episodes[i]].mean()
        diffs[i] = (a / b - 1) * 100 if relative else a - b
    low, high = np.percentile(diffs, [2.5, 97.5])
    mark = "≈ " if low <= 0 <= high else ""
    point = (mine.mean() / theirs.mean() - 1) * 100 if relative else mine.mean() - theirs.mean()
    unit = " %" if relative else ""
    return f"{mark}{point:+.2f}{unit} [{low:+.2f}, {high:+.2f}]"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--arm", default="own-penalty50-ent03-sumo-brake4")
    parser.add_argument("--results", type=Path, default=HERE / "results")
    parser.add_argument(
        "--at", default="dense", help="the evaluations' AT (30ep: the training cell, to compare)"
    )
    args = parser.parse_args()
    print(
        "| row | simulator | policy | with a collision | delay [s] "
        "| vs same-mix [s] | vs heuristic [s] |"
    )
    print("|---|---|---|---|---|---|---|")
    pooled_lines = []
    for backend in ("highway", "sumo"):
        evals = args.results / args.arm / "eval" / f"test-{backend}-{args.at}"
        refs = args.results / "reference" / "eval" / f"test-{backend}-{args.at}"
        runs = {
            p.name: read(p) for p in sorted(evals.glob("*-s*")) if (p / "episodes.csv").is_file()
        }
        missing = [
            n for n in ("same-mix", "heuristic") if not (refs / n / "episodes.csv").is_file()
        ]
        if missing:  # run eval.sh with ARM=reference and the same AT and GRID first
            raise SystemExit(f"dense_rows.py: error: no {', '.join(missing)} results in {refs}")
        references = {name: read(refs / name) for name in ("same-mix", "heuristic")}
        for row in sorted(references["same-mix"], key=lambda k: int(k[1])):
            episodes = sorted(references["same-mix"][row])
            label = f"{row[0]} N = {row[1]}, rho = {row[2]}"

            def column(evaluation, row=row, episodes=episodes, field=0) -> np.ndarray:
                return np.array([evaluation[row][e][field] for e in episodes])  # (P,)

            ref = {name: column(ev)[None] for name, ev in references.items()}  # (1, P)
            by_variant: dict[str, list[np.ndarray]] = defaultdict(list)
            speeds: dict[str, list[np.ndarray]] = defaultdict(list)
            for name, evaluation in runs.items():
                crashes = sum(evaluation[row][e][2] for e in episodes)
                mine = column(evaluation)[None]  # (1, P)
                variant = name.rsplit("-s", 1)[0]  # diacc-nopsar-s2 -> diacc-nopsar
                by_variant[variant].append(mine[0])
                speeds[variant].append(column(evaluation, field=1))
                print(
                    f"| {label} | {backend} | {name} | {crashes} of {len(episodes)} | "
                    f"{mine.mean():.2f} | {change(mine, ref['same-mix'])} | "
                    f"{change(mine, ref['heuristic'])} |"
                )
            for name in ("same-mix", "heuristic"):
                crashes = sum(references[name][row][e][2] for e in episodes)
                print(f"| {label} | {backend} | {name} | {crashes} of {len(episodes)} | "
                      f"{ref[name].mean():.2f} | | |")  # fmt: skip
            if {"diacc-nopsar", "mappo"} <= by_variant.keys():
                diacc, mappo = (np.stack(by_variant[v]) for v in ("diacc-nopsar", "mappo"))
                fast, slow = (np.stack(speeds[v]) for v in ("diacc-nopsar", "mappo"))
                pooled_lines.append(
                    f"| {label} | {backend} | {len(diacc)} / {len(mappo)} | "
                    f"{diacc.mean():.2f} / {mappo.mean():.2f} | {change(diacc, mappo)} | "
                    f"{fast.mean():.2f} / {slow.mean():.2f} | "
                    f"{change(fast, slow, relative=True)} |"
                )
    if not pooled_lines:  # an arm without mappo runs
        return
    print("\nThe variants pooled over their seeds, diacc-nopsar against mappo (same episodes):\n")
    print(
        "| row | simulator | seeds (diacc-nopsar / mappo) | delay [s] | change [s] "
        "| mean speed [m/s] | change (the paper's measure) |"
    )
    print("|---|---|---|---|---|---|---|")
    print("\n".join(pooled_lines))


if __name__ == "__main__":
    main()
