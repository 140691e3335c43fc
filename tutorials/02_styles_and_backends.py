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
# # 2. Driving styles, and one scenario on two simulators
#
# Human drivers in DIACC come in three styles: *aggressive*, *normal* and
# *cautious*. Each style is described **once** (`diacc.config.STYLE_PRESETS`)
# and both simulators read the same description: the IDM car-following terms
# mean the same on both, and the lane-change terms exist in two images
# (MOBIL on `highway`, LC2013 on `sumo`).
#
# In this tutorial we
#
# 1. print the style parameters of both presets (`paper`, `realistic`),
# 2. measure the time headway each style keeps in simulated traffic, and
# 3. run the same seeded scenario on `highway` and on `sumo` (libsumo) and
#    compare their speed profiles in one figure.

# %%
import os
from dataclasses import fields
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from diacc.config import STYLE_MIXES, STYLE_NAMES, STYLE_PRESETS, SimConfig
from diacc.envs.safety import SAME_COL, lane_leaders_followers, pair_kinematics
from diacc.sim.backends.base import CavCommands, make_backend
from diacc.sim.maps import load_map
from diacc.sim.scenario import Scenario

OUT = Path(os.environ.get("DIACC_TUTORIAL_OUT", "tutorial_out")) / "02_styles_and_backends"
OUT.mkdir(parents=True, exist_ok=True)

# %% [markdown]
# ## The style parameters
#
# `time_headway_s`, `min_gap_m`, `accel_mps2` and `decel_mps2` are the IDM
# terms (SUMO's `tau`, `minGap`, `accel`, `decel`). `politeness` and
# `lc_gain_threshold_mps2` drive MOBIL; the three `lc_*` fields are SUMO's
# LC2013 parameters. The presets differ only for cautious drivers: `paper`
# keeps the authors' values, with which a cautious SUMO driver may never
# merge and stop at the lane end; `realistic` (the default) lets every driver
# merge.

# %%
names = [f.name for f in fields(STYLE_PRESETS["paper"][0]) if f.name != "name"]


def cell(value) -> str:
    """One table entry: numbers and flags as numbers, unset options as '-'."""
    return f"{'-':>12}" if value is None else f"{float(value):>12.2f}"


for preset, styles in STYLE_PRESETS.items():
    print(f"preset {preset!r}")
    print(f"  {'parameter':<24}" + "".join(f"{s.name:>12}" for s in styles))
    for name in names:
        print(f"  {name:<24}" + "".join(cell(getattr(s, name)) for s in styles))
print("\nHDV style mixes (aggressive, normal, cautious):", STYLE_MIXES)

# %% [markdown]
# The IDM desired gap at a steady speed `v` is `s0 + v T`: the minimum gap plus
# the time headway times the speed. At 20 m/s an aggressive driver wants
# 19 m, a cautious one 26 m; that difference is what makes a cautious-heavy
# mix (D2) slower through a bottleneck than an aggressive-heavy one (D3).

# %%
styles = STYLE_PRESETS[SimConfig().style_preset]
speed_grid_mps = np.linspace(0.0, 25.0, 51)  # (G,)
for s in styles:
    print(f"{s.name:>10}: desired gap at 20 m/s = {s.min_gap_m + 20.0 * s.time_headway_s:.1f} m")

# %% [markdown]
# ## The same scenario on both backends
#
# `make_backend(name, road)` builds either simulator for the same map; the SUMO
# network is built from the map with `netconvert` on first use and cached.
# Both insert exactly the same population for a given scenario and seed, and
# both return the same `TrafficState` arrays, so the analysis code below does
# not know which simulator produced the data.

# %%
road = load_map("train-25")
scenario = Scenario(n_vehicles=25, cav_penetration=0.0, style_mix="D1")
SEED = 3


def simulate(backend_name: str, max_steps: int = 120) -> list:
    """All states of one pure-HDV episode (until every vehicle has left)."""
    backend = make_backend(backend_name, road)
    try:
        state = backend.reset(scenario, SEED)  # a batch of one env: (1, V) arrays
        idle = CavCommands.idle(state.n_vehicles)
        states = [state]
        while state.active.any() and len(states) <= max_steps:
            state = backend.step(idle)
            states.append(state)
    finally:
        backend.close()
    return states


runs = {name: simulate(name) for name in ("highway", "sumo")}
for name, states in runs.items():
    print(f"{name:>8}: {len(states) - 1} steps, {states[-1].arrived.sum()} vehicles arrived")
assert np.array_equal(runs["highway"][0].style, runs["sumo"][0].style)  # same population

# %% [markdown]
# ## Time headway by style, measured
#
# For every vehicle and step we look up its leader in the same lane
# (`lane_leaders_followers`) and the bumper-to-bumper gap (`pair_kinematics`,
# the paper's `d_long`). The time headway is gap / speed, kept for vehicles
# driving faster than 5 m/s. Both simulators should order the styles the same
# way: aggressive shortest, cautious longest.


# %%
def time_headways(states: list) -> dict[str, np.ndarray]:
    """Style name -> measured time headways [s] over all steps of an episode."""
    out = {name: [] for name in STYLE_NAMES}
    for state in states:
        everyone = np.arange(state.n_vehicles)[None]  # (1, V): every vehicle of env 0
        leader = lane_leaders_followers(state, everyone).front[..., SAME_COL]  # (1, V)
        kin = pair_kinematics(state, everyone, leader)
        keep = state.active & kin.valid & (state.speed_mps > 5.0) & ~state.is_cav  # (1, V)
        headway_s = kin.d_long_m[keep] / state.speed_mps[keep]
        for code, name in enumerate(STYLE_NAMES):
            out[name].append(headway_s[state.style[keep] == code])
    return {name: np.concatenate(parts) for name, parts in out.items()}


headways = {name: time_headways(states) for name, states in runs.items()}
for backend_name, by_style in headways.items():
    medians = ", ".join(f"{k} {np.median(v):.2f} s" for k, v in by_style.items() if v.size)
    print(f"{backend_name:>8} median time headway: {medians}")

fig, (ax_gap, ax_box) = plt.subplots(1, 2, figsize=(12, 4.2))
for s in styles:
    ax_gap.plot(speed_grid_mps, s.min_gap_m + speed_grid_mps * s.time_headway_s, label=s.name)
ax_gap.set(xlabel="speed [m/s]", ylabel="IDM desired gap s0 + vT [m]", title="Desired gap by style")
ax_gap.legend()
positions, data, labels = [], [], []
for b, (backend_name, by_style) in enumerate(headways.items()):
    for k, name in enumerate(STYLE_NAMES):
        if by_style[name].size:
            positions.append(k * 3 + b)
            data.append(np.clip(by_style[name], 0.0, 6.0))
            labels.append(f"{name}\n{backend_name}")
ax_box.boxplot(data, positions=positions, widths=0.8, showfliers=False)
ax_box.set_xticks(positions, labels, fontsize=7)
ax_box.set(ylabel="time headway [s]", title="Measured headway to the leader")
fig.tight_layout()
styles_png = OUT / "styles_headway.png"
fig.savefig(styles_png, dpi=110)
plt.close(fig)
print("wrote", styles_png)

# %% [markdown]
# ## Speed profiles of the two backends
#
# Mean speed per 25 m of road (left) and over time (right). The two
# simulators share the map, the population and the style parameters, but not
# their internals (SUMO's LC2013 lane changing and its merge behaviour at lane
# ends differ from our MOBIL + forced-merge rule), so the curves agree in
# shape, not sample by sample. This is why DIACC trains on the fast `highway`
# backend and *validates* on SUMO (tutorial 7).


# %%
def speed_profile(states: list, bins_m: np.ndarray) -> np.ndarray:
    """Mean speed of all active samples per position bin (nan where empty)."""
    x_m = np.concatenate([s.x_m[s.active] for s in states])  # (M,)
    v_mps = np.concatenate([s.speed_mps[s.active] for s in states])  # (M,)
    which = np.clip(np.digitize(x_m, bins_m) - 1, 0, len(bins_m) - 2)
    sums = np.bincount(which, weights=v_mps, minlength=len(bins_m) - 1)
    counts = np.bincount(which, minlength=len(bins_m) - 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, sums / counts, np.nan)


bins_m = np.arange(0.0, road.length_m + 1.0, 25.0)
fig, (ax_x, ax_t) = plt.subplots(1, 2, figsize=(12, 4.2))
for seg, start_m, end_m in zip(
    road.segments, road.segment_starts_m, road.segment_ends_m, strict=True
):
    if seg.kind != "multilane":
        ax_x.axvspan(start_m, end_m, color="0.88", zorder=0)
for backend_name, states in runs.items():
    ax_x.plot(0.5 * (bins_m[1:] + bins_m[:-1]), speed_profile(states, bins_m), label=backend_name)
    mean_v = [s.speed_mps[s.active].mean() for s in states if s.active.any()]
    ax_t.plot(np.arange(len(mean_v)), mean_v, label=backend_name)
ax_x.set(
    xlabel="position x [m]", ylabel="mean speed [m/s]", title="Speed over position", ylim=(0, 26)
)
ax_t.set(xlabel="time [s]", ylabel="mean speed [m/s]", title="Speed over time", ylim=(0, 26))
ax_x.legend()
ax_t.legend()
fig.suptitle(f"{road.name}, N={scenario.n_vehicles} pure HDV, mix D1, seed {SEED}")
fig.tight_layout()
backends_png = OUT / "backends_speed.png"
fig.savefig(backends_png, dpi=110)
plt.close(fig)
print("wrote", backends_png)
