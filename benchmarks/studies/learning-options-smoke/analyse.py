"""Table of a learning-options smoke run (benchmarks/studies/learning-options-smoke/run.sh).

Per setting and seed: the means over the last third of the updates of the
training episodes' speeds, arrivals, collisions and PSAR rewrite rates, and the
PPO diagnostics (KL, clip fraction, entropy). ``team_reward`` is not compared:
the options change the reward.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

COLUMNS = (
    ("episode/mean_speed_mps", "speed m/s"),
    ("episode/mean_cav_speed_mps", "CAV speed m/s"),
    ("episode/arrived_fraction", "arrived"),
    ("episode/collision", "collisions"),
    ("psar/cancel_lc", "cancel-LC"),
    ("psar/force_brake", "force-brake"),
    ("psar/suppr_accel", "suppr-accel"),
    ("approx_kl", "KL"),
    ("clipfrac", "clip frac"),
    ("entropy", "entropy"),
)


def tail_means(run: Path) -> dict[str, float]:
    rows = [json.loads(line) for line in (run / "progress.jsonl").read_text().splitlines()]
    tail = rows[len(rows) - max(1, len(rows) // 3) :]
    out = {"steps": rows[-1]["global_step"]}
    for key, _ in COLUMNS:
        values = [r[key] for r in tail if key in r and r[key] == r[key]]
        out[key] = sum(values) / len(values) if values else float("nan")
    return out


def main() -> None:
    root, seeds = Path(sys.argv[1]), sys.argv[2:]
    print("| setting | seed | steps | " + " | ".join(label for _, label in COLUMNS) + " |")
    print("|---" * (3 + len(COLUMNS)) + "|")
    # Every run directory <setting>-s<seed> there, today's defaults first.
    runs = {
        p.name.rsplit("-s", 1)[0] for p in root.iterdir() if p.name.rsplit("-s", 1)[-1] in seeds
    }
    for setting in sorted(runs, key=lambda name: (name != "default", name)):
        for seed in seeds:
            if not (root / f"{setting}-s{seed}").is_dir():
                continue
            m = tail_means(root / f"{setting}-s{seed}")
            cells = " | ".join(f"{m[key]:.3f}" for key, _ in COLUMNS)
            print(f"| {setting} | {seed} | {m['steps']} | {cells} |")


if __name__ == "__main__":
    main()
