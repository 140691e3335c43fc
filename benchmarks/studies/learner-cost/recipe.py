"""The recipe over its seeds on `test`: is every seed within 5 % of their mean, none collapsed?

    python benchmarks/studies/learner-cost/recipe.py > benchmarks/studies/learner-cost/results/recipe.md

Reads what ``recipe.sh`` wrote: each ``base`` seed's 30 `test` episodes per simulator
(``results/base/eval/test-<backend>-200k/diacc-s<seed>/``) and the references' on the same
episodes (``results/reference/eval/test-<backend>/``), and each run's last collapse check
(``runs/diacc-s<seed>/train.log``, written at every checkpoint). Prints per seed and
simulator the mean delay per vehicle, its distance from the seeds' mean, the change against
same-mix and the heuristic paired by episode (mean with a 95 % normal interval), the
episodes with a collision and the greedy policy's most frequent action at the end of
training. Every seed is listed, none left out.
"""

from __future__ import annotations

import csv
import math
import re
import statistics
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
#: The target: every seed's test delay within this share of the seeds' mean.
SPREAD = 0.05
#: The collapse check's threshold (diacc.learn: one greedy action on >= 99 % of decisions).
COLLAPSE_SHARE = 99.0


def delays_by_seed(folder: Path) -> dict[str, float]:
    """Episode seed -> delay per vehicle (s) of one evaluation."""
    with (folder / "episodes.csv").open() as fh:
        return {r["seed"]: float(r["delay_per_vehicle_s"]) for r in csv.DictReader(fh)}


def collisions(folder: Path) -> int:
    with (folder / "episodes.csv").open() as fh:
        return sum(int(float(r["collision"])) > 0 for r in csv.DictReader(fh))


def paired_change(mine: dict[str, float], ref: dict[str, float]) -> str:
    """Mean change in s per vehicle on the shared episodes, 95 % normal interval."""
    diffs = [mine[s] - ref[s] for s in mine if s in ref]
    if len(diffs) < 2:
        return "-"
    mean = statistics.fmean(diffs)
    half = 1.96 * statistics.stdev(diffs) / math.sqrt(len(diffs))
    return f"{mean:+.2f} [{mean - half:+.2f}, {mean + half:+.2f}]"


def last_collapse_check(run: Path) -> tuple[str, float]:
    """The greedy top action and its share (%) of the run log's last collapse check."""
    found = re.findall(r"greedy '(\w+)' on ([\d.]+)%", (run / "train.log").read_text())
    return (found[-1][0], float(found[-1][1])) if found else ("?", math.nan)


def main() -> None:
    runs = sorted((RESULTS / "base/runs").glob("diacc-s*/"), key=lambda p: int(p.name[7:]))
    print("| simulator | seed | delay / vehicle [s] | from the seeds' mean | vs same-mix [s] "
          "| vs heuristic [s] | with a collision | greedy at the end |")
    print("|---|---|---|---|---|---|---|---|")
    verdicts = []
    for backend in ("highway", "sumo"):
        refs = {
            name: delays_by_seed(RESULTS / f"reference/eval/test-{backend}/{name}")
            for name in ("same-mix", "heuristic")
            if (RESULTS / f"reference/eval/test-{backend}/{name}/episodes.csv").is_file()
        }
        evaluated = [
            (run, RESULTS / f"base/eval/test-{backend}-200k/{run.name}") for run in runs
        ]
        evaluated = [(run, f) for run, f in evaluated if (f / "episodes.csv").is_file()]
        if not evaluated:
            continue
        means = {run.name: statistics.fmean(delays_by_seed(f).values()) for run, f in evaluated}
        centre = statistics.fmean(means.values())
        for run, folder in evaluated:
            mine = delays_by_seed(folder)
            action, share = last_collapse_check(run)
            collapsed = " (collapsed)" if share >= COLLAPSE_SHARE else ""
            print(
                f"| {backend} | {run.name[6:]} | {means[run.name]:.2f} | "
                f"{(means[run.name] - centre) / centre:+.1%} | "
                f"{paired_change(mine, refs['same-mix']) if 'same-mix' in refs else '-'} | "
                f"{paired_change(mine, refs['heuristic']) if 'heuristic' in refs else '-'} | "
                f"{collisions(folder)} of {len(mine)} | {action} {share:.0f} %{collapsed} |"
            )
        for name, ref in refs.items():
            print(f"| {backend} | {name} | {statistics.fmean(ref.values()):.2f} | | | | | |")
        widest = max(abs(m - centre) / centre for m in means.values())
        verdicts.append(
            f"{backend}: {len(means)} seeds, mean {centre:.2f} s, widest distance "
            f"{widest:.1%} ({'within' if widest <= SPREAD else 'not within'} {SPREAD:.0%})"
        )
    print()
    for line in verdicts:
        print(f"- {line}")


if __name__ == "__main__":
    main()
