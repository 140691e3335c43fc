"""Training collision rate against steps for runs of ``diacc train``: CSV + figure.

The learning check of the safety issue: the paper's training scenario
(``train-50``, N = 25, 10 CAVs, highway), 50k steps, before and after PSAR
could stop a CAV::

    diacc train --variant diacc --map train-50 --envs 4 --steps 50000 --seed 1 --run-dir R
    python benchmarks/studies/training_curves.py --out runs/psar-learning-check \\
        before=R_BEFORE after=R_AFTER

Each row of ``curves.csv`` is one PPO update: the share of the episodes that
ended in that update's rollout with a collision, and their mean speeds.

Labels of the form ``NAME/sSEED`` are seeds of one configuration: their
last-window means are then also summarised per configuration (mean and
spread over seeds) in ``summary.md``.
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from diacc.experiments.plots import step_axis

COLUMNS = {
    "collision_rate": "episode/collision",
    "collided_vehicles": "episode/n_collisions",
    "mean_speed_mps": "episode/mean_speed_mps",
    "mean_cav_speed_mps": "episode/mean_cav_speed_mps",
    "p_sce": "episode/p_sce",
    "arrived_fraction": "episode/arrived_fraction",
    "delay_per_vehicle_s": "episode/delay_per_vehicle_s",
}
#: Panels of the figure: (column, y label).
PANELS = (
    ("collision_rate", "training episodes with a collision"),
    ("collided_vehicles", "vehicles in a collision per episode"),
    ("mean_cav_speed_mps", "mean CAV speed in training [m/s]"),
    ("arrived_fraction", "vehicles that arrived [share]"),
    ("delay_per_vehicle_s", "delay per vehicle in training [s]"),
)
#: Panels whose values are shares (y axis 0-1).
SHARES = ("collision_rate", "arrived_fraction")


def smooth(values: list[float], window: int) -> list[float]:
    """Trailing moving average over ``window`` updates (the first ones average what exists)."""
    out = []
    for i in range(len(values)):
        chunk = values[max(0, i - window + 1) : i + 1]
        out.append(sum(chunk) / len(chunk))
    return out


def read_run(run_dir: Path) -> list[dict]:
    rows = [json.loads(line) for line in (run_dir / "progress.jsonl").open() if line.strip()]
    return [
        {"step": r["global_step"], **{k: r.get(src, float("nan")) for k, src in COLUMNS.items()}}
        for r in rows
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="LABEL=RUN_DIR")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--title", default="diacc on highway, train-50, N = 25, 10 CAVs, 4 envs")
    parser.add_argument("--smooth", type=int, default=1, help="moving average over updates")
    parser.add_argument("--window", type=int, default=10_000, help="steps of first/last summary")
    parser.add_argument(
        "--max-step", type=int, default=None, help="cut every run at this many steps (equal steps)"
    )
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    runs = {label: read_run(Path(path)) for label, path in (r.split("=", 1) for r in args.runs)}
    if args.max_step is not None:
        runs = {k: [r for r in rows if r["step"] <= args.max_step] for k, rows in runs.items()}
    with (args.out / "curves.csv").open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["run", "step", *COLUMNS])
        for label, rows in runs.items():
            for r in rows:
                writer.writerow([label, r["step"], *(f"{r[k]:.4f}" for k in COLUMNS)])
    fig, axes = plt.subplots(1, len(PANELS), figsize=(5 * len(PANELS), 3.6))
    # Seeds of one configuration (labels NAME/sSEED) share a colour and one legend entry.
    groups = list(dict.fromkeys(label.rsplit("/s", 1)[0] for label in runs))
    colours = {g: f"C{i % 10}" for i, g in enumerate(groups)}
    named: set[str] = set()
    for label, rows in runs.items():
        steps = [r["step"] for r in rows]
        group = label.rsplit("/s", 1)[0]
        legend = None if group in named else (group if group != label else label)
        named.add(group)
        for ax, (column, _) in zip(axes, PANELS, strict=True):
            values = smooth([r[column] for r in rows], args.smooth)
            ax.plot(steps, values, label=legend, color=colours[group], lw=1.2)
    for ax, (column, ylabel) in zip(axes, PANELS, strict=True):
        step_axis(ax)
        ax.set_ylabel(ylabel)
        if column in SHARES:
            ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    suffix = f" (moving average over {args.smooth} updates)" if args.smooth > 1 else ""
    fig.suptitle(args.title + suffix, fontsize=10)
    fig.tight_layout()
    fig.savefig(args.out / "curves.png", dpi=100)
    for label, rows in runs.items():
        first = [r for r in rows if r["step"] <= args.window]
        last = [r for r in rows if r["step"] > rows[-1]["step"] - args.window]
        mean = lambda xs, k: sum(x[k] for x in xs) / len(xs)  # noqa: E731
        print(
            f"{label} ({rows[-1]['step']} steps): collision rate "
            f"{mean(first, 'collision_rate'):.2f} in the first {args.window} steps, "
            f"{mean(last, 'collision_rate'):.2f} in the last {args.window}; CAV speed "
            f"{mean(first, 'mean_cav_speed_mps'):.1f} -> "
            f"{mean(last, 'mean_cav_speed_mps'):.1f} m/s; "
            f"arrived {mean(first, 'arrived_fraction'):.2f} -> {mean(last, 'arrived_fraction'):.2f}"
        )

    write_seed_summary(runs, args.out / "summary.md", args.window)


def write_seed_summary(runs: dict[str, list[dict]], path: Path, window: int) -> None:
    """Per configuration (label ``NAME/sSEED``): mean +- sd over seeds of the last window."""
    groups: dict[str, list[list[dict]]] = {}
    for label, rows in runs.items():
        if "/s" in label:
            groups.setdefault(label.rsplit("/s", 1)[0], []).append(rows)
    if not groups:
        return
    lines = [
        f"Last {window} environment steps of each run, mean +- sd over seeds",
        "",
        "| configuration | seeds | steps | " + " | ".join(PANEL_COLUMNS) + " |",
        "|---|---|---|" + "---|" * len(PANEL_COLUMNS),
    ]
    for name, seeds in groups.items():
        cells = []
        for column in PANEL_COLUMNS:
            per_seed = []
            for rows in seeds:
                last = [r[column] for r in rows if r["step"] > rows[-1]["step"] - window]
                per_seed.append(sum(last) / len(last))
            sd = statistics.stdev(per_seed) if len(per_seed) > 1 else float("nan")
            cells.append(f"{statistics.mean(per_seed):.3f} +- {sd:.3f}")
        steps = min(rows[-1]["step"] for rows in seeds)
        lines.append(f"| {name} | {len(seeds)} | {steps} | " + " | ".join(cells) + " |")
    path.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


#: Columns of the per-configuration summary.
PANEL_COLUMNS = (
    "collision_rate",
    "collided_vehicles",
    "mean_cav_speed_mps",
    "mean_speed_mps",
    "arrived_fraction",
    "delay_per_vehicle_s",
)


if __name__ == "__main__":
    main()
