"""Outflow against inflow: the bottleneck's classic figure (issue 44).

A bottleneck fed by continuous demand passes what enters until the inflow
reaches its capacity; above it a queue forms and, with human drivers, the
outflow often *falls* below the capacity (the capacity drop), which is what
automated vehicles are meant to win back. This module reads ``diacc eval``
results of demand cells (one directory per policy and inflow, as
``benchmarks/studies/demand-training/flow.sh`` writes them) and draws, per backend, the mean
outflow (``throughput_vph``: vehicles past the bottleneck's end per hour after
the warm-up) of every policy against the inflow, with a 95 % bootstrap
interval over episodes, the line outflow = inflow (every vehicle served), and,
where pure-HDV results are among them, the pure-HDV capacity (its largest mean
outflow) and its drop at the highest inflow. A second row shows the delay per
vehicle. A point with episodes that had a collision is drawn as a red-edged
cross labelled "k/n crashed" (their delay and outflow are counted to the
horizon under evaluation's ``on_collision = "remove"``; results made before it
ended at the crash). ``diacc plot flow DIR ... --out FILE``.

Series are named by the directory above each ``q<inflow>`` folder (or the
results directory's own name): ``flow/highway/same-mix/q3600`` is ``same-mix``
on ``highway``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from diacc.experiments.evaluate import EvaluationError, load_episodes
from diacc.experiments.paired import BOOTSTRAP_SEED, CONFIDENCE, RESAMPLES
from diacc.experiments.plots import PlotError, _pyplot, _save
from diacc.experiments.sametraffic import check_same_traffic

#: The series whose largest outflow is the capacity the figure marks.
CAPACITY_SERIES = "pure-hdv"


@dataclass(frozen=True)
class FlowPoint:
    """One policy at one inflow on one backend: episode means and intervals."""

    backend: str
    series: str
    inflow_vph: float
    episodes: int
    outflow_vph: float
    outflow_low: float
    outflow_high: float
    delay_s: float
    delay_low: float
    delay_high: float
    crashed: int = 0  # episodes with a collision (marked in the figure)


def mean_interval(values: np.ndarray) -> tuple[float, float, float]:
    """Mean and its seeded percentile-bootstrap interval (one value: a zero-width one)."""
    values = np.asarray(values, dtype=np.float64)
    mean = float(values.mean())
    if len(values) < 2:
        return mean, mean, mean
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    means = values[rng.integers(0, len(values), (RESAMPLES, len(values)))].mean(axis=1)
    tail = 50.0 * (1.0 - CONFIDENCE)
    low, high = np.percentile(means, [tail, 100.0 - tail])
    return mean, float(low), float(high)


def _series_name(results_dir: Path) -> str:
    if results_dir.name.startswith("q") and results_dir.name[1:].replace(".", "").isdigit():
        return results_dir.parent.name
    return results_dir.name


def load_flow(roots: list[str | Path]) -> list[FlowPoint]:
    """Every (backend, series, inflow) of the demand episodes found under ``roots``."""
    groups: dict[tuple[str, str, float], list[dict[str, str]]] = {}
    files = [
        path
        for root in map(Path, roots)
        for path in ([root] if root.name == "episodes.csv" else sorted(root.rglob("episodes.csv")))
    ]
    if not files:
        raise PlotError(f"no episodes.csv under {', '.join(map(str, roots))}")
    columns = []  # (series, meta, demand rows) of each file: one traffic per point
    for path in files:
        try:  # the validating loader: meta present, numbers numbers, cells that exist
            meta, rows = load_episodes(path.parent)
        except EvaluationError as exc:
            raise PlotError(str(exc)) from None
        series = _series_name(path.parent)
        columns.append((series, meta, [r for r in rows if float(r.get("inflow_vph") or 0) > 0]))
        for row in rows:
            try:
                inflow = float(row.get("inflow_vph") or 0.0)
            except ValueError:
                bad = row.get("inflow_vph")
                raise PlotError(f"{path}: inflow_vph {bad!r} is not a number") from None
            if inflow > 0:  # release cells have no inflow to plot against
                groups.setdefault((row["backend"], series, inflow), []).append(row)
    if not groups:
        raise PlotError(f"no demand cell (inflow_vph > 0) in {len(files)} episodes.csv file(s)")
    check_same_traffic(columns, lambda row: f"{row['backend']} at {row['inflow_vph']} veh/h")
    points = []
    for (backend, series, inflow), rows in sorted(groups.items()):
        try:
            outflow = np.array([float(r["throughput_vph"]) for r in rows])
            delay = np.array([float(r["delay_per_vehicle_s"]) for r in rows])
            crashed = sum(int(float(r.get("collision") or 0) > 0) for r in rows)
        except (KeyError, ValueError) as exc:
            raise PlotError(f"{series} at {inflow:g} veh/h: unusable flow field ({exc})") from None
        points.append(
            FlowPoint(
                backend,
                series,
                inflow,
                len(rows),
                *mean_interval(outflow),
                *mean_interval(delay),
                crashed=crashed,
            )
        )
    return points


def capacity(points: list[FlowPoint], backend: str) -> tuple[float, float] | None:
    """(capacity, drop) of pure HDV on ``backend``: its largest mean outflow, and the
    relative fall from it to the outflow at its highest inflow (0: no drop, also where
    nothing passed at all: no capacity to fall from); None without pure-HDV points."""
    own = sorted(
        (p for p in points if p.backend == backend and p.series == CAPACITY_SERIES),
        key=lambda p: p.inflow_vph,
    )
    if not own:
        return None
    top = max(p.outflow_vph for p in own)
    return top, (top - own[-1].outflow_vph) / top if top > 0 else 0.0


def plot_flow(roots: list[str | Path], out: str | Path) -> tuple[list[Path], list[FlowPoint]]:
    """Draw the figure (PNG + PDF at ``out``); return its paths and the points drawn."""
    points = load_flow(roots)
    backends = sorted({p.backend for p in points})
    plt = _pyplot()
    fig, axes = plt.subplots(
        2, len(backends), figsize=(5.5 * len(backends), 7.5), sharex="col", squeeze=False
    )
    for column, backend in enumerate(backends):
        top, bottom = axes[0][column], axes[1][column]
        mine = [p for p in points if p.backend == backend]
        for series in dict.fromkeys(p.series for p in mine):
            line = sorted((p for p in mine if p.series == series), key=lambda p: p.inflow_vph)
            x = [p.inflow_vph for p in line]
            for ax, mean, low, high in (
                (top, "outflow_vph", "outflow_low", "outflow_high"),
                (bottom, "delay_s", "delay_low", "delay_high"),
            ):
                y = np.array([getattr(p, mean) for p in line])
                err = np.array(
                    [
                        [y_i - getattr(p, low), getattr(p, high) - y_i]
                        for p, y_i in zip(line, y, strict=True)
                    ]
                ).T
                drawn = ax.errorbar(x, y, yerr=err, marker="o", capsize=3, label=series)
                for p, y_i in zip(line, y, strict=True):  # a crash is never left unmarked
                    if p.crashed:
                        colour = drawn.lines[0].get_color()
                        ax.plot(p.inflow_vph, y_i, marker="X", ms=11, color=colour, mec="red")
                        ax.annotate(
                            f"{p.crashed}/{p.episodes} crashed",
                            (p.inflow_vph, y_i),
                            textcoords="offset points",
                            xytext=(4, -10),
                            fontsize=7,
                            color="red",
                        )
        inflows = sorted({p.inflow_vph for p in mine})
        (served,) = top.plot(
            inflows, inflows, color="grey", lw=0.8, ls=":", label="outflow = inflow"
        )
        marked = capacity(points, backend)
        if marked is not None:
            cap, drop = marked
            top.axhline(cap, color="black", lw=0.8, ls="--")
            top.annotate(
                f"pure-HDV capacity {cap:.0f} veh/h; drop {drop:.0%} at {inflows[-1]:.0f}",
                (inflows[-1], cap),
                textcoords="offset points",
                xytext=(0, 4),
                ha="right",
                fontsize=8,
            )
        top.set_title(backend)
        top.set_ylabel("outflow (veh/h)")
        bottom.set_ylabel("delay per vehicle (s)")
        bottom.set_xlabel("inflow (veh/h)")
        top.legend(handles=[served], fontsize=8, loc="upper left")
        bottom.legend(fontsize=8, loc="upper left")  # the policies, where the curves leave room
    return _save(fig, out), points
