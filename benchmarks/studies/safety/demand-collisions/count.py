"""Episodes with a collision per backend, policy and inflow: after (a run of ``run.sh``)
beside before (the committed demand results of the same protocol), issue 57.

    python benchmarks/studies/safety/demand-collisions/count.py RUN_DIR [--before DIR]

Prints a Markdown table: crashed episodes / episodes (HDV-HDV pairs), and the mean delay
per vehicle (s) of each side over the episode seeds both played (the before side's
crashed episodes were cut short at the crash; after, episodes run on to the horizon).
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

BEFORE = Path("benchmarks/studies/demand-training/results")


def read(root: Path) -> dict[tuple[str, str, int], list[dict[str, str]]]:
    """(backend, policy, inflow) -> episode rows of every ``episodes.csv`` under ``root``."""
    out: dict[tuple[str, str, int], list[dict[str, str]]] = {}
    for path in sorted(root.rglob("q*/episodes.csv")):
        backend, policy = path.parts[-4], path.parts[-3]
        with path.open(newline="") as f:
            out[(backend, policy, int(path.parent.name[1:]))] = list(csv.DictReader(f))
    return out


def crashed(rows: list[dict[str, str]]) -> str:
    hit = sum(int(float(r["collision"])) for r in rows)
    hdv = sum(int(float(r["n_hdv_collisions"])) for r in rows)
    return f"{hit}/{len(rows)}" + (f" ({hdv} HDV-HDV)" if hdv else "")


def mean_delay(rows: list[dict[str, str]], seeds: set[str]) -> str:
    values = [float(r["delay_per_vehicle_s"]) for r in rows if r["seed"] in seeds]
    return f"{sum(values) / len(values):.1f}" if values else "—"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--before", type=Path, default=BEFORE / "flow-every-cav")
    args = parser.parse_args()
    after, before = read(args.run_dir), read(args.before)
    if not after:
        raise SystemExit(f"count.py: error: no q*/episodes.csv under {args.run_dir}")
    print(
        "| backend | policy | inflow (veh/h) | crashed before | crashed after "
        "| delay before (s) | delay after (s) |"
    )
    print("|---|---|---|---|---|---|---|")
    for key in sorted(after):
        rows, old = after[key], before.get(key, [])
        seeds = {r["seed"] for r in rows} & {r["seed"] for r in old}
        print(
            f"| {key[0]} | {key[1]} | {key[2]} | {crashed(old) if old else '—'} | "
            f"{crashed(rows)} | {mean_delay(old, seeds)} | {mean_delay(rows, seeds)} |"
        )


if __name__ == "__main__":
    main()
