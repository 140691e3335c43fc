# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 1. A highway bottleneck, with human drivers only
#
# Every experiment in DIACC happens on one **map**: a straight 1.3 km route cut
# into segments, some of which lose lanes (the *bottleneck*). In this tutorial
# we
#
# 1. load a shipped map and look at its segments,
# 2. fill it with 25 human-driven vehicles (HDVs, no CAV at all) and simulate
#    them on the fast `highway` backend,
# 3. plot speed over position and time (a time-space diagram), and
# 4. save one rendered frame of the road.
#
# Every file this tutorial writes goes to the folder named by the environment
# variable `DIACC_TUTORIAL_OUT` (default `./tutorial_out`).

# %%
import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # no display needed; figures are saved as PNG
import matplotlib.pyplot as plt
import numpy as np

from diacc.console import metric_lines, print_lines
from diacc.envs.metrics import EpisodeRecorder
from diacc.sim.backends.base import CavCommands, make_backend
from diacc.sim.maps import available_maps, load_map
from diacc.sim.scenario import Scenario
from diacc.sim.viewer import Viewer

OUT = Path(os.environ.get("DIACC_TUTORIAL_OUT", "tutorial_out")) / "01_bottleneck"
OUT.mkdir(parents=True, exist_ok=True)

# %% [markdown]
# ## The map
#
# Maps are plain TOML files in `maps/`. `load_map` validates them and returns a
# frozen `Map` with derived geometry. Lanes are numbered in one absolute frame
# (lane 0 is the rightmost lane of the widest cross-section), so a lane keeps
# its number through the bottleneck.

# %%
print("shipped maps:", ", ".join(available_maps()))
road = load_map("train-50")
print(f"{road.name}: {road.description}")
for seg, start_m, end_m in zip(
    road.segments, road.segment_starts_m, road.segment_ends_m, strict=True
):
    print(
        f"  {start_m:6.0f}-{end_m:6.0f} m  {seg.kind:<12} {seg.lanes} lanes  "
        f"{seg.speed_limit_mps:.0f} m/s"
    )
# (S, L) table: which absolute lane exists in which segment (1 = exists)
exists = road.lane_exists()
print("  segment       " + "  ".join(f"lane {lane}" for lane in range(exists.shape[1])))
for seg, row in zip(road.segments, exists, strict=True):
    print(f"  {seg.kind:<12}  " + "  ".join(f"{int(x):^6}" for x in row))

# %% [markdown]
# ## Pure-HDV traffic on the `highway` backend
#
# A `Scenario` says *what* traffic to insert (vehicle count, CAV share, HDV
# style mix); the seed given to `reset` makes the draw reproducible. With
# `cav_penetration=0.0` every vehicle is an HDV driven by IDM car following and
# MOBIL lane changes, and the backend's command input is ignored: we pass
# `CavCommands.idle` each step.
#
# The backend returns a `TrafficState`, always a batch: arrays with a leading
# env axis, `(E, V)` (a backend may simulate many envs at once; this one holds
# one, E = 1), so row 0 (`state.x_m[0]`) is our env's one entry per vehicle. We
# stack the fields we need into `(T, V)` arrays for plotting.

# %%
scenario = Scenario(n_vehicles=25, cav_penetration=0.0, style_mix="D1")
backend = make_backend("highway", road)
viewer = Viewer(road, backend.sim)
state = backend.reset(scenario, seed=0)  # a batch of one env
recorder = EpisodeRecorder(road)
recorder.record(state)  # the recorder takes the backend's batch as it is
idle = CavCommands.idle(state.n_vehicles)

time_s, x_m, speed_mps, active = [], [], [], []
frame_step = 35  # which step to render below: the queue at the lane drop
frame = None
for _ in range(120):
    time_s.append(state.time_s[0])
    x_m.append(state.x_m[0].copy())
    speed_mps.append(state.speed_mps[0].copy())
    active.append(state.active[0].copy())
    if state.step[0] == frame_step:
        frame = viewer.draw(state)  # (H, W, 3) uint8, highway-env's own renderer
    if not state.active.any():
        break
    state = backend.step(idle)
    recorder.record(state)
backend.close()

time_s = np.array(time_s)  # (T,)
x_m, speed_mps, active = np.array(x_m), np.array(speed_mps), np.array(active)  # (T, V)
print(f"simulated {time_s[-1]:.0f} s; {state.arrived.sum()} of {state.n_vehicles} vehicles arrived")

# %% [markdown]
# The `EpisodeRecorder` turns the same stream of states into the paper's
# metrics: mean speed, share of vehicles with a waiting event (speed < 3 m/s),
# share with a safety-critical event, and more.

# %%
metrics = recorder.summary()
# `metric_lines` rounds, writes shares in percent and leaves out what does not
# apply (a segment kind this map lacks, CAV speeds without CAVs), where the raw
# metrics hold nan.
kinds = tuple(dict.fromkeys(seg.kind for seg in road.segments))
print_lines(metric_lines(metrics, kinds))

# %% [markdown]
# ## Speed over position and time
#
# Left: a time-space diagram, one dot per vehicle and second, coloured by
# speed; the shaded band is the reduction segment. Slow (red) streaks that
# start at the bottleneck are the queue. Right: mean speed per 25 m bin of
# position; the dip sits at the lane drop, where vehicles in the ending lanes
# must merge.

# %%
reduction = [
    (s, e)
    for seg, s, e in zip(road.segments, road.segment_starts_m, road.segment_ends_m, strict=True)
    if seg.kind != "multilane"
]
t_grid = np.broadcast_to(time_s[:, None], x_m.shape)  # (T, V)

fig, (ax_ts, ax_bin) = plt.subplots(1, 2, figsize=(12, 4.5))
for start_m, end_m in reduction:
    ax_ts.axhspan(start_m, end_m, color="0.85", zorder=0)
    ax_bin.axvspan(start_m, end_m, color="0.85", zorder=0, label="reduction")
points = ax_ts.scatter(
    t_grid[active], x_m[active], c=speed_mps[active], s=4, cmap="RdYlGn", vmin=0, vmax=25
)
fig.colorbar(points, ax=ax_ts, label="speed [m/s]")
ax_ts.set(xlabel="time [s]", ylabel="position x [m]", title="Time-space diagram (pure HDV)")

bins_m = np.arange(0.0, road.length_m + 25.0, 25.0)
which = np.digitize(x_m[active], bins_m) - 1  # bin of each sample
sums = np.bincount(which, weights=speed_mps[active], minlength=len(bins_m))
counts = np.bincount(which, minlength=len(bins_m))
with np.errstate(invalid="ignore"):
    mean_by_bin = sums / counts
centres_m = bins_m + 12.5
ax_bin.plot(centres_m[counts > 0], mean_by_bin[counts > 0], marker=".")
ax_bin.set(xlabel="position x [m]", ylabel="mean speed [m/s]", title="Speed profile", ylim=(0, 26))
ax_bin.legend()
fig.tight_layout()
speed_png = OUT / "speed_time_space.png"
fig.savefig(speed_png, dpi=110)
plt.close(fig)
print("wrote", speed_png)

# %% [markdown]
# ## A rendered frame
#
# `Viewer.draw(state)` draws a state of either backend with highway-env's renderer
# (offscreen, no window). Vehicles are coloured by style: orange aggressive,
# blue normal, yellow cautious; the sand-coloured hatch marks lanes that do not exist
# in the bottleneck.

# %%
assert frame is not None
frame_png = OUT / f"frame_step{frame_step}.png"
plt.imsave(frame_png, frame)
print("wrote", frame_png, "shape", frame.shape)
