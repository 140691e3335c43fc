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
# # 5. The team reward: softmin aggregation and its temperature
#
# All CAVs share one team reward (paper eq. reward_all):
#
# `R = w_e * sum_i w_i r_e^i + w_g * r_g + r_done`
#
# * `r_e^i` is CAV *i*'s ego reward (speed, warning and collision distance,
#   time penalty), `r_g` a global speed term, `r_done` an exit bonus;
# * the weights `w_i = exp(-r_e^i / tau) / sum_j exp(-r_e^j / tau)` are a
#   **softmin**: the lower a CAV's reward, the more it weighs. At a high
#   temperature `tau` they approach the plain mean; at a low one, the minimum.
#   The team is then judged by its worst-off member, which pushes CAVs to help
#   the one stuck behind a merge instead of racing ahead;
# * `tau` is annealed linearly from 2 to 0.05 over the first half of training.
#   Every environment emits R at the temperature it is given (`env.tau`);
#   whoever trains sets it from the schedule: `diacc train` before each
#   rollout, a PettingZoo user with `AnnealTemperature(env, total_steps)`,
#   so the PettingZoo `rewards` are the R that `diacc train` trains on.
#
# We plot the weights against `tau`, the schedule over training, and the
# reward terms of a real traffic state.

# %%
import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from diacc.config import RewardConfig, TrainConfig
from diacc.envs.env import BottleneckEnv, EnvConfig
from diacc.envs.reward import reward_terms, softmin_weights, team_reward, temperature

OUT = Path(os.environ.get("DIACC_TUTORIAL_OUT", "tutorial_out")) / "05_rewards"
OUT.mkdir(parents=True, exist_ok=True)
cfg = RewardConfig()
print(cfg)

# %% [markdown]
# ## Softmin weights against the temperature
#
# Five CAVs with ego rewards from comfortable (4.5, near the maximum of 5) to
# slow (1.0). At `tau = 2` the weights are spread out; at `tau = 0.05` almost
# all weight sits on the worst CAV, and the aggregated ego reward
# `sum_i w_i r_e^i` has moved from near the mean to the minimum.

# %%
ego_reward = np.array([4.5, 4.0, 3.5, 2.5, 1.0])  # (C,)
alive = np.ones_like(ego_reward, dtype=bool)  # (C,)
taus = np.geomspace(0.03, 20.0, 120)  # (M,)
weights = np.stack([softmin_weights(ego_reward, alive, tau) for tau in taus])  # (M, C)
aggregated = weights @ ego_reward  # (M,)

for tau in (cfg.tau_init, 0.5, cfg.tau_final):
    w = softmin_weights(ego_reward, alive, tau)
    print(f"tau = {tau:5.2f}: weights {np.round(w, 3)}, aggregated {w @ ego_reward:+.2f}")
print(f"mean {ego_reward.mean():+.2f}, min {ego_reward.min():+.2f}")

# A CAV that has left the route (alive False) gets no weight at all.
gone = alive.copy()
gone[-1] = False
print("stuck CAV has left:", np.round(softmin_weights(ego_reward, gone, cfg.tau_final), 3))

fig, (ax_w, ax_agg, ax_tau) = plt.subplots(1, 3, figsize=(15, 4.2))
for c, r in enumerate(ego_reward):
    ax_w.plot(taus, weights[:, c], label=f"CAV {c}: r_e = {r:+.1f}")
ax_w.set(xscale="log", xlabel="temperature tau", ylabel="softmin weight w_i", title="Weights")
ax_w.legend(fontsize=8)
ax_agg.plot(taus, aggregated, color="black", label="sum_i w_i r_e^i")
ax_agg.axhline(ego_reward.mean(), ls="--", color="tab:blue", label="mean")
ax_agg.axhline(ego_reward.min(), ls="--", color="tab:red", label="min")
for tau in (cfg.tau_init, cfg.tau_final):
    ax_agg.axvline(tau, color="0.6", lw=0.8)
ax_agg.set(
    xscale="log",
    xlabel="temperature tau",
    ylabel="aggregated ego reward",
    title="Aggregate: from mean to min",
)
ax_agg.legend(fontsize=8)

# %% [markdown]
# ## The temperature schedule
#
# `temperature(step, total_steps, cfg)` gives `tau` at any environment step:
# linear from `tau_init` to `tau_final` over `tau_anneal_fraction` of the run,
# then constant. The trainer's rollouts read it once per update.

# %%
total_steps = TrainConfig().total_steps
steps = np.linspace(0, total_steps, 301).astype(int)  # (P,)
tau_curve = np.array([temperature(int(s), total_steps, cfg) for s in steps])  # (P,)
print(
    f"tau at 0, 25 %, 50 %, 100 % of {total_steps:,} steps:",
    [round(temperature(int(f * total_steps), total_steps, cfg), 3) for f in (0, 0.25, 0.5, 1.0)],
)
ax_tau.plot(steps / 1e6, tau_curve)
ax_tau.set(xlabel="environment steps [millions]", ylabel="tau", title="Annealing schedule")
fig.tight_layout()
softmin_png = OUT / "softmin_and_schedule.png"
fig.savefig(softmin_png, dpi=110)
plt.close(fig)
print("wrote", softmin_png)

# %% [markdown]
# ## The reward of a real traffic state
#
# `reward_terms(state, cav_index, road, cfg)` returns every term per env and CAV, and
# `team_reward(ego, alive, global_reward, completion, delay, tau, cfg)` makes the
# team reward of them at a temperature. We drive the CAVs with random actions
# (what an untrained actor does) for up to 30 steps, then score the last state
# at the start and at the end of the schedule. Random driving soon ends in a
# collision, even behind PSAR (see the end of tutorial 4): the CAVs involved get
# the collision penalty
# `p_ec = -10`, and at a low temperature that one CAV is nearly all of the
# team's ego reward. This is exactly the pressure the softmin is meant to
# create: no CAV can profit while another one crashes or is stuck.

# %%
env = BottleneckEnv(EnvConfig(backend="highway", map="train-50"))
env.reset_arrays(seed=2)
rng = np.random.default_rng(0)
for _ in range(30):
    out = env.step_arrays(rng.integers(0, 5, size=env.n_cavs))
    if out.terminated or out.truncated:
        break
state = out.state  # a batch of one env
t = reward_terms(state, env.cav_index[None], env.road, cfg).unbatched(0)  # env 0's (C,) terms
env.close()
terms = {
    tau: team_reward(t.ego, t.alive, t.global_reward, t.completion, t.delay, tau, cfg)
    for tau in (cfg.tau_init, cfg.tau_final)
}

cavs = np.flatnonzero(t.alive)
print(f"plain mean of the ego rewards: {t.ego[cavs].mean():+.3f}")
print(f"t = {state.time_s[0]:.0f} s, {cavs.size} CAVs on the road")
print("collided pairs (vehicle indices):", state.collisions[:, 1:].tolist())
for tau, tt in terms.items():
    print(
        f"tau = {tau:4.2f}: ego (softmin) {tt.ego_softmin:+.3f}, global {t.global_reward:+.3f}, "
        f"completion {t.completion:.0f}, total R = {tt.total:+.3f}"
    )

fig, (ax_terms, ax_wt) = plt.subplots(1, 2, figsize=(13, 4.2))
parts = {
    "speed": cfg.speed_weight * t.speed,
    "warning": cfg.warning_weight * t.warning,
    "collision": cfg.collision_weight * t.collision,
    "time penalty": cfg.time_penalty_weight * t.time_penalty,
}
bottom_pos = np.zeros(cavs.size)
bottom_neg = np.zeros(cavs.size)
for name, values in parts.items():
    v = values[cavs]
    base = np.where(v >= 0, bottom_pos, bottom_neg)
    ax_terms.bar(np.arange(cavs.size), v, bottom=base, label=name)
    bottom_pos += np.maximum(v, 0)
    bottom_neg += np.minimum(v, 0)
ax_terms.plot(np.arange(cavs.size), t.ego[cavs], "k_", ms=18, mew=2, label="ego reward r_e")
ax_terms.set_xticks(np.arange(cavs.size), [f"cav_{c}" for c in cavs], fontsize=8)
ax_terms.set(ylabel="weighted term", title="Ego reward terms per CAV")
ax_terms.legend(fontsize=8)
width = 0.4
for k, (tau, tt) in enumerate(terms.items()):
    ax_wt.bar(
        np.arange(cavs.size) + (k - 0.5) * width,
        tt.softmin_weight[cavs],
        width,
        label=f"tau = {tau}",
    )
ax_wt.set_xticks(np.arange(cavs.size), [f"cav_{c}" for c in cavs], fontsize=8)
ax_wt.set(ylabel="softmin weight", title="Who counts in the team reward")
ax_wt.legend()
fig.tight_layout()
terms_png = OUT / "reward_terms.png"
fig.savefig(terms_png, dpi=110)
plt.close(fig)
print("wrote", terms_png)
