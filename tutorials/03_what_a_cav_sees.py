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
# # 3. What a CAV sees
#
# A connected automated vehicle (CAV) does not see the whole road. Its actor
# network (TAIE, the paper's traffic-aware interaction encoder) gets, per step:
#
# * its own state (position, speed, lane, distance to the end of its lane),
# * its **6 nearest vehicles** in its own and the adjacent lanes, with a
#   5-step history, split into two graphs: **CAV-HDV** (human drivers) and
#   **CAV-CAV** (other CAVs, which also report the action they just took),
# * **lane statistics** of its own, left and right lane (count, density, mean
#   speed, CAV share within 100 m),
# * the static road table and its own previous actions.
#
# The shared `ObservationBuilder` makes these arrays from any backend's
# `TrafficState`; the environment `BottleneckEnv` calls it every step. Here we
# run a few steps, pick one CAV and draw its two neighbour graphs and its lane
# statistics.

# %%
import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from diacc.envs.actions import ACCELERATE
from diacc.envs.env import ACTION_NAMES, BottleneckEnv, EnvConfig
from diacc.envs.observation import COUNT_SCALE, DENSITY_SCALE_VEH_PER_KM, DX_SCALE_M

OUT = Path(os.environ.get("DIACC_TUTORIAL_OUT", "tutorial_out")) / "03_what_a_cav_sees"
OUT.mkdir(parents=True, exist_ok=True)

# Feature order of a neighbour node and of a lane-statistics row (see the
# docstring of diacc.envs.observation, which fixes the layout).
NODE_FEATURES = ("dx", "dy", "dv", "heading", "v", "is_cav")
LANE_FEATURES = ("count", "density", "mean speed", "CAV share")
LANE_SLOTS = ("ego lane", "left lane", "right lane")
DX, DY = NODE_FEATURES.index("dx"), NODE_FEATURES.index("dy")

# %% [markdown]
# ## Run the environment for a few steps
#
# `BottleneckEnv` is a PettingZoo `ParallelEnv`; the batched methods
# `reset_arrays` / `step_arrays` return the observations of all CAVs at once
# as one `ActorObs` of arrays with a leading CAV axis `C`. We let every CAV
# ask for `accelerate` for 15 steps (PSAR, tutorial 4, keeps it safe) so that
# traffic has spread out and the history is filled.

# %%
env = BottleneckEnv(EnvConfig(backend="highway", map="train-25"))
obs, critic = env.reset_arrays(seed=5)
print("agents:", env.possible_agents)
for _ in range(15):
    out = env.step_arrays(np.full(env.n_cavs, ACCELERATE))
    obs, critic = out.actor_obs, out.critic_state
state = out.state  # a batch of one env: row 0 of its (1, V) arrays is our env
for name, value in vars(obs).items():
    print(f"  {name:<16} {str(value.shape):<18} {value.dtype}")

# %% [markdown]
# ## Pick a CAV with both kinds of neighbours
#
# `hdv_mask` and `cav_mask` (C, K) say which of the K = 6 slots of each graph
# hold a real vehicle; the two sets together are the 6 nearest vehicles.

# %%
n_hdv = obs.hdv_mask.sum(axis=1)  # (C,)
n_cav = obs.cav_mask.sum(axis=1)  # (C,)
score = np.where(obs.alive, np.minimum(n_hdv, n_cav) * 10 + n_hdv + n_cav, -1)
c = int(np.argmax(score))
ego = int(env.cav_index[c])
print(f"{env.possible_agents[c]} is vehicle {ego}: {n_hdv[c]} HDV and {n_cav[c]} CAV neighbours")
print(
    f"  x = {state.x_m[0, ego]:.1f} m, lane {state.lane[0, ego]}, "
    f"speed {state.speed_mps[0, ego]:.1f} m/s"
)

# The builder's own neighbour table (V, K) agrees with the two actor graphs.
nbr, nbr_mask = env.neighbours  # (V, K) each
print("  its neighbours (vehicle indices):", sorted(nbr[ego][nbr_mask[ego]].tolist()))

# %% [markdown]
# ## The two neighbour graphs
#
# Node features are relative to the ego's *current* position: `dx` in units of
# 50 m, `dy` in lane widths. Multiplying back gives metres. The last history
# step (index -1) is now; earlier steps trace each neighbour's trajectory in
# the ego's frame. In the CAV graph every node carries the action that CAV
# executed at the previous step (`cav_prev_action`).

# %%
lane_w_m = env.road.lane_width_m


def to_metres(nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K, T, F) normalised nodes -> dx, dy in metres, each (K, T)."""
    return nodes[..., DX] * DX_SCALE_M, nodes[..., DY] * lane_w_m


fig = plt.figure(figsize=(13, 8))
ax_road = fig.add_subplot(2, 1, 1)
ax_hdv = fig.add_subplot(2, 3, 4)
ax_cav = fig.add_subplot(2, 3, 5)
ax_lane = fig.add_subplot(2, 3, 6)

# (a) Bird's-eye view in road coordinates: every vehicle near the ego.
window_m = 70.0
near = state.active[0] & (np.abs(state.x_m[0] - state.x_m[0][ego]) <= window_m)  # (V,)
ax_road.axhspan(0.0, env.road.max_lanes * lane_w_m, color="0.9", zorder=0)
for lane in range(1, env.road.max_lanes):
    ax_road.axhline(lane * lane_w_m, color="white", lw=1, ls="--", zorder=1)
colours = np.where(state.is_cav[0], "tab:green", "tab:blue")
colours[ego] = "tab:red"
ax_road.scatter(
    state.x_m[0][near], state.y_m[0][near], c=colours[near], s=160, marker="s", zorder=3
)
for nodes, mask, colour in (
    (obs.hdv_nodes[c], obs.hdv_mask[c], "tab:blue"),
    (obs.cav_nodes[c], obs.cav_mask[c], "tab:green"),
):
    dx_m, dy_m = to_metres(nodes)  # (K, T)
    for k in np.flatnonzero(mask):
        x1, y1 = state.x_m[0][ego] + dx_m[k, -1], state.y_m[0][ego] + dy_m[k, -1]
        ax_road.plot(
            [state.x_m[0][ego], x1], [state.y_m[0][ego], y1], color=colour, lw=1.5, zorder=2
        )
ax_road.set(
    xlim=(state.x_m[0][ego] - window_m, state.x_m[0][ego] + window_m),
    ylim=(0, env.road.max_lanes * lane_w_m),
    xlabel="x [m]",
    ylabel="y [m]",
    title=f"Road around the ego (red): edges to its HDV (blue) and CAV (green) neighbours, "
    f"t = {state.time_s[0]:.0f} s",
)

# (b), (c) The two graphs in the ego frame, with 5-step trajectories.
for ax, kind, nodes, mask, colour in (
    (ax_hdv, "CAV-HDV graph", obs.hdv_nodes[c], obs.hdv_mask[c], "tab:blue"),
    (ax_cav, "CAV-CAV graph", obs.cav_nodes[c], obs.cav_mask[c], "tab:green"),
):
    dx_m, dy_m = to_metres(nodes)  # (K, T)
    ego_dx, ego_dy = to_metres(obs.ego_hist[c][None])  # (1, T)
    ax.plot(ego_dx[0], ego_dy[0], color="tab:red", alpha=0.5)
    ax.scatter([0.0], [0.0], color="tab:red", s=120, marker="s", zorder=3, label="ego")
    for k in np.flatnonzero(mask):
        ax.plot([0.0, dx_m[k, -1]], [0.0, dy_m[k, -1]], color=colour, lw=1.5)
        ax.plot(dx_m[k], dy_m[k], color=colour, alpha=0.4, ls=":")  # history
        ax.scatter(dx_m[k, -1], dy_m[k, -1], color=colour, s=90, marker="s", zorder=3)
        if kind == "CAV-CAV graph":
            action = ACTION_NAMES[int(obs.cav_prev_action[c, k])]
            ax.annotate(
                action,
                (dx_m[k, -1], dy_m[k, -1]),
                textcoords="offset points",
                xytext=(4, 6),
                fontsize=8,
            )
    ax.axhline(0.0, color="0.8", lw=0.8)
    ax.axvline(0.0, color="0.8", lw=0.8)
    ax.set(
        xlabel="dx [m] (ahead +)",
        ylabel="dy [m] (left +)",
        ylim=(-1.5 * lane_w_m, 1.5 * lane_w_m),
        title=f"{kind}: {mask.sum()} nodes",
    )

# (d) Lane statistics of ego / left / right lane, back in physical units.
stats = obs.lane_stats[c]  # (3, 4) normalised
physical = stats * np.array([COUNT_SCALE, DENSITY_SCALE_VEH_PER_KM, env.road.max_speed_mps, 1.0])
bar_w = 0.25
for s, slot in enumerate(LANE_SLOTS):
    if not obs.lane_mask[c, s]:
        print(f"  {slot} does not exist here (masked)")
        continue
    ax_lane.bar(np.arange(len(LANE_FEATURES)) + (s - 1) * bar_w, stats[s], bar_w, label=slot)
    print(
        f"  {slot:<10}: {physical[s, 0]:.0f} vehicles, {physical[s, 1]:.0f} veh/km, "
        f"mean speed {physical[s, 2]:.1f} m/s, CAV share {physical[s, 3]:.0%}"
    )
ax_lane.set_xticks(np.arange(len(LANE_FEATURES)), LANE_FEATURES, fontsize=8)
ax_lane.set(ylabel="normalised value", title="Lane statistics (within 100 m)")
ax_lane.legend(fontsize=8)
fig.tight_layout()
graph_png = OUT / "cav_neighbour_graphs.png"
fig.savefig(graph_png, dpi=110)
plt.close(fig)
print("wrote", graph_png)

# %% [markdown]
# ## The critic's view
#
# The centralised critic (ITDR + C-IEC) sees *every* vehicle, padded to
# `max_vehicles` rows with a mask, the same neighbour table as a global graph,
# per-lane statistics of the whole route and global traffic features. It is
# only used during training.

# %%
for name, value in vars(critic).items():
    print(f"  {name:<15} {str(value.shape):<10} {value.dtype}")
print(f"{critic.node_mask.sum()} vehicles on the road, {critic.neighbour_mask.sum()} graph edges")

# %% [markdown]
# ## Many environments, one step
#
# The environment above is a batch of one: its step is `EnvBatch.step`
# (`diacc/envs/batch.py`), written once for E environments with a leading env
# axis. Training steps E of them together (`make_vector_env`: one batched
# simulator on highway, automatic resets), so every observation gains that axis:
# `(E, C, ...)` for the actors, `(E, ...)` for the critic. Each env of the batch
# is exactly what it would be alone: env `e` of the vector env plays the
# episodes that a batch holding env `e` alone plays (same seeds, same numbers).

# %%
from diacc.envs.vector import SyncVectorEnv, make_vector_env  # noqa: E402

config = EnvConfig(backend="highway", map="train-25")
envs = make_vector_env(config, 4, run_seed=0)  # 4 envs, one batched simulator
alone = SyncVectorEnv(config, 4, run_seed=0, env_indices=[2])  # env 2 of the same run, alone
obs_batch, critic_batch = envs.reset(first_episode=0)
obs_alone, _ = alone.reset(first_episode=0)
rng = np.random.default_rng(0)
for _ in range(10):
    actions = rng.integers(0, 5, (envs.n_envs, envs.n_cavs))  # (E, C)
    out, out_alone = envs.step(actions), alone.step(actions[2:3])
print("actor self_state:", out.actor_obs.self_state.shape)  # (E, C, 6)
print("critic nodes:", out.critic_state.nodes.shape)  # (E, N, F)
print("ego rewards (E, C):", out.ego.shape, " episode ends (E,):", out.terminated | out.truncated)
same = np.array_equal(out.actor_obs.self_state[2], out_alone.actor_obs.self_state[0])
print("env 2 in the batch == env 2 alone:", same)
assert same
envs.close()
alone.close()
env.close()
