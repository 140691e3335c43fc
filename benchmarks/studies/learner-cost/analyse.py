"""CPU-minutes against validation delay, per run and arm, of the learner-cost study.

    cd benchmarks/studies/learner-cost && python analyse.py > results/summary.md

Reads each run's ``progress.jsonl`` (the CPU seconds of every update's rollout and
learner, ``rollout_cpu_s`` + ``learner_cpu_s``) and the validation evaluations
``run.sh`` made at its stages (``results/<arm>/eval/validation-highway-<k>k/``).
The target is the shipped agent's delay per vehicle on the same validation
episodes (``results/shipped/``); a run reaches it at the first stage whose mean
delay is within ``TOLERANCE`` of it (10 episodes do not tell 10.8 from 11.0 s).
Every run is listed, none left out.
"""

from __future__ import annotations

import csv
import json
import math
import statistics
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
#: A stage reaches the target when its delay is at most this much above it.
TOLERANCE = 0.05


def episodes(folder: Path) -> list[dict[str, str]]:
    with (folder / "episodes.csv").open() as fh:
        return list(csv.DictReader(fh))


def mean_delay_s(rows: list[dict[str, str]]) -> float:
    return statistics.fmean(float(r["delay_per_vehicle_s"]) for r in rows)


def cpu_minutes_to(progress: Path, step: int) -> float:
    """Rollout + learner CPU of the run's updates up to env step ``step``."""
    total_s = 0.0
    for line in progress.read_text().splitlines():
        row = json.loads(line)
        if row["global_step"] > step:
            break
        total_s += row["rollout_cpu_s"] + row["learner_cpu_s"]
    return total_s / 60


def main() -> None:
    shipped = sorted((RESULTS / "shipped/eval/validation-highway").glob("*/episodes.csv"))
    target_s = mean_delay_s(episodes(shipped[0].parent)) if shipped else math.nan
    print(
        f"Target: the shipped agent's validation delay, {target_s:.2f} s per vehicle "
        f"(reached within {TOLERANCE:.0%}: at most {target_s * (1 + TOLERANCE):.2f} s).\n"
    )
    print("| arm | run | env steps | CPU min | delay / vehicle [s] | with a collision |")
    print("|---|---|---|---|---|---|")
    reach: dict[str, list[float]] = {}
    for run in sorted(RESULTS.glob("*/runs/*/")):
        arm = run.parents[1].name
        first = math.nan
        stages = sorted(
            RESULTS.glob(f"{arm}/eval/validation-highway-*k/{run.name}/episodes.csv"),
            key=lambda p: int(p.parent.parent.name.rsplit("-", 1)[1][:-1]),
        )
        for csv_path in stages:
            step = 1000 * int(csv_path.parent.parent.name.rsplit("-", 1)[1][:-1])
            rows = episodes(csv_path.parent)
            delay_s = mean_delay_s(rows)
            cpu_min = cpu_minutes_to(run / "progress.jsonl", step)
            crashed = sum(int(float(r["collision"])) > 0 for r in rows)
            print(
                f"| {arm} | {run.name} | {step:,} | {cpu_min:.1f} | {delay_s:.2f} | "
                f"{crashed} / {len(rows)} |"
            )
            if math.isnan(first) and delay_s <= target_s * (1 + TOLERANCE):
                first = cpu_min
        reach.setdefault(arm, []).append(first)
    print("\n| arm | runs | CPU min to the target (first stage within the tolerance), per run |")
    print("|---|---|---|")
    for arm, minutes in reach.items():
        shown = ", ".join("not reached" if math.isnan(m) else f"{m:.1f}" for m in minutes)
        print(f"| {arm} | {len(minutes)} | {shown} |")


if __name__ == "__main__":
    main()
