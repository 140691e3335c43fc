"""The time-space diagram of one episode: where traffic slows, and for how long.

One dot per (vehicle, decision step), at (time, position), coloured by speed
(red slow, green free flow); the reduction segments are shaded, so a queue
shows as a red streak growing backwards from the lane drop. A second panel
gives the mean speed per 25 m of road. The episode is played through the
environment (:class:`~diacc.envs.episode.EpisodeDriver`) by any policy, on either
backend, so ``diacc plot timespace`` draws pure-HDV traffic and a trained
agent alike. Tutorial 1 builds the same figure by hand.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from diacc.experiments.grid import Cell
from diacc.experiments.plots import PlotError, _pyplot, _save
from diacc.experiments.policies import EvalSettings, PolicySpec
from diacc.experiments.render import episode_driver
from diacc.sim.maps import Map

#: Width of the speed-profile bins along the road.
BIN_M = 25.0
#: Colour scale of the speed dots (m/s); the default speed limit is ~25 m/s.
SPEED_RANGE_MPS = (0.0, 25.0)


@dataclass
class Trajectories:
    """Every decision step of one episode as (T, V) arrays."""

    time_s: np.ndarray  # (T,)
    x_m: np.ndarray  # (T, V)
    speed_mps: np.ndarray  # (T, V)
    active: np.ndarray  # (T, V) bool
    is_cav: np.ndarray  # (V,) bool


def record_trajectories(
    spec: PolicySpec, cell: Cell, steps: int | None, settings: EvalSettings, seed: int
) -> tuple[Trajectories, Map, str, str]:
    """Play one episode of ``spec`` (at most ``steps`` decisions; None: all of it);
    (trajectories, map, policy label, HDV style preset the episode ran with)."""
    if steps is not None and steps < 1:
        raise PlotError(f"--steps must be >= 1, got {steps}")
    policy, driver = episode_driver(spec, cell, steps, settings)
    try:
        state = driver.reset(seed)
        frames = [state]  # batches of one env
        while not driver.done:
            frames.append(driver.step())
    finally:
        driver.close()
    trajectories = Trajectories(
        time_s=np.concatenate([s.time_s for s in frames]),  # (T,)
        x_m=np.concatenate([s.x_m for s in frames]),  # (T, V)
        speed_mps=np.concatenate([s.speed_mps for s in frames]),
        active=np.concatenate([s.active for s in frames]),
        is_cav=frames[0].is_cav[0].copy(),
    )
    return trajectories, driver.road, policy.describe()["policy"], driver.cfg.sim.style_preset


def speed_profile(traj: Trajectories, length_m: float) -> tuple[np.ndarray, np.ndarray]:
    """(bin centres (B,), mean speed per bin (B,), nan where no vehicle passed)."""
    edges_m = np.arange(0.0, length_m + BIN_M, BIN_M)  # (B + 1,)
    x, v = traj.x_m[traj.active], traj.speed_mps[traj.active]  # (S,)
    which = np.clip(np.digitize(x, edges_m) - 1, 0, len(edges_m) - 2)
    sums = np.bincount(which, weights=v, minlength=len(edges_m) - 1)
    counts = np.bincount(which, minlength=len(edges_m) - 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
    return edges_m[:-1] + BIN_M / 2, mean


def draw_timespace(traj: Trajectories, road: Map, caption: str, out: str | Path) -> list[Path]:
    """The two-panel figure (time-space diagram, speed profile); writes PNG and PDF."""
    plt = _pyplot()
    fig, (ax_ts, ax_bin) = plt.subplots(
        1, 2, figsize=(12, 4.6), gridspec_kw={"width_ratios": [1.6, 1]}
    )
    reduction = [
        (s, e)
        for seg, s, e in zip(road.segments, road.segment_starts_m, road.segment_ends_m, strict=True)
        if seg.kind != "multilane"
    ]
    for i, (start_m, end_m) in enumerate(reduction):
        label = "lane reduction" if i == 0 else None
        ax_ts.axhspan(start_m, end_m, color="0.88", zorder=0, label=label)
        ax_bin.axvspan(start_m, end_m, color="0.88", zorder=0, label=label)
    t_grid = np.broadcast_to(traj.time_s[:, None], traj.x_m.shape)  # (T, V)
    hdv = traj.active & ~traj.is_cav[None, :]
    cav = traj.active & traj.is_cav[None, :]
    lo, hi = SPEED_RANGE_MPS
    points = ax_ts.scatter(
        t_grid[hdv], traj.x_m[hdv], c=traj.speed_mps[hdv], s=5, cmap="RdYlGn", vmin=lo, vmax=hi
    )
    if cav.any():  # CAVs as outlined triangles in the same colour scale
        ax_ts.scatter(
            t_grid[cav],
            traj.x_m[cav],
            c=traj.speed_mps[cav],
            s=14,
            marker="^",
            cmap="RdYlGn",
            vmin=lo,
            vmax=hi,
            edgecolors="k",
            linewidths=0.3,
            label="CAV",
        )
    fig.colorbar(points, ax=ax_ts, label="speed [m/s]", pad=0.01)
    ax_ts.set(xlabel="time [s]", ylabel="position along the route [m]", title="Time-space diagram")
    ax_ts.set_ylim(0.0, road.length_m)
    ax_ts.legend(loc="upper left", fontsize=8)
    centres_m, mean_mps = speed_profile(traj, road.length_m)
    ax_bin.plot(centres_m, mean_mps, marker=".", color="#1f77b4", label="all vehicles")
    ax_bin.set(
        xlabel="position along the route [m]",
        ylabel="mean speed [m/s]",
        title=f"Speed profile ({BIN_M:.0f} m bins)",
        ylim=(0.0, hi + 2.0),
        xlim=(0.0, road.length_m),
    )
    ax_bin.grid(alpha=0.3)
    ax_bin.legend(loc="lower left", fontsize=8)
    fig.text(0.01, -0.02, caption, fontsize=9, ha="left", va="top", wrap=True)
    fig.tight_layout()
    return _save(fig, out)


def plot_timespace(
    spec: PolicySpec,
    cell: Cell,
    out: str | Path,
    steps: int | None,
    settings: EvalSettings,
    seed: int | None = None,
) -> list[Path]:
    """Play one episode and draw its time-space diagram; the caption names policy,
    backend, map, traffic and seed (the seed defaults to that of eval episode 0)."""
    seed = cell.seed(0, settings.stream) if seed is None else seed
    traj, road, label, preset = record_trajectories(spec, cell, steps, settings, seed)
    caption = (
        f"{label} on {settings.backend}, map {road.name}: {cell.n_vehicles} vehicles "
        f"({int(traj.is_cav.sum())} CAVs), mix {cell.style_mix}, style preset {preset}, "
        f"seed {seed}, "
        f"{len(traj.time_s) - 1} decision steps ({traj.time_s[-1]:.0f} s). "
        "Dots: one per vehicle and step, coloured by speed; shaded: lane reduction."
    )
    return draw_timespace(traj, road, caption, out)
