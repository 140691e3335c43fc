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
# # 8. A trained agent in your own Python loop
#
# The `diacc` command evaluates checkpoints for you. Here we drive one
# ourselves, through the public PettingZoo API only, as you would to plug a
# trained DIACC agent into your own experiment:
#
# 1. load a shipped checkpoint with `diacc.load_policy`,
# 2. make the environment it was trained in (`policy.make_env()`, a PettingZoo
#    `ParallelEnv`, the same class `diacc.parallel_env` returns),
# 3. run an episode: `policy.act(observations)` returns one action per CAV and
#    keeps each CAV's recurrent (GRU) state; CAVs that leave are forgotten,
# 4. read the episode's metrics from `infos` and save a rendered frame,
# 5. compare greedy and sampled actions, and the trained agent with CAVs that
#    only ever keep their lane.
#
# Every file this tutorial writes goes to `$DIACC_TUTORIAL_OUT/08_trained_agent_in_python`.

# %%
import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

import diacc

OUT = Path(os.environ.get("DIACC_TUTORIAL_OUT", "tutorial_out")) / "08_trained_agent_in_python"
OUT.mkdir(parents=True, exist_ok=True)
# A shipped agent, from the installed package (a clone's or a wheel's): any directory works.
CHECKPOINT = diacc.CHECKPOINTS_DIR / "diacc-train50-paper-congestion-s1.pt"

# %% [markdown]
# ## Load the agent and its environment
#
# A checkpoint carries the configuration it was trained with: map, traffic,
# observation layout, PSAR. `make_env` builds exactly that environment; keyword
# arguments change parts of it, as they do for `diacc.parallel_env`.

# %%
policy = diacc.load_policy(CHECKPOINT)
env = policy.make_env(render_mode="rgb_array")
print(f"variant {policy.variant}, map {env.config.map}, backend {env.config.backend}")
print(f"agents: {env.possible_agents}")
print(f"one agent's observation: {len(env.observation_space('cav_0').spaces)} named arrays")
print(f"the critic's state: {env.state_space.shape[0]} numbers")

# %% [markdown]
# ## One episode
#
# The loop is PettingZoo's: step while any agent is on the road. For
# PettingZoo the episode ends when the last CAV leaves (or time runs out, or
# vehicles collide), even if human drivers are still on the road. At that
# step every agent's `infos` carries `episode_metrics`, measured over the
# steps played: the mean speed of all vehicles,
# p(WE) and p(SCE) (the share of vehicles with a waiting or a safety-critical
# event), collisions, and how many vehicles arrived.


# %%
def run_episode(env, choose, seed):
    """Play one episode with ``choose(observations) -> actions``; returns its metrics
    and the frame of step 30 (or of the last step, if the episode is shorter)."""
    observations, _ = env.reset(seed=seed)
    frame, step = None, 0
    while env.agents:
        observations, _, _, _, infos = env.step(choose(observations))
        step += 1
        if step <= 30 and env.render_mode == "rgb_array":
            frame = env.render()
    metrics = next(iter(infos.values()))["episode_metrics"]
    return metrics, frame


def greedy(observations):
    return policy.act(observations)


policy.reset(seed=0)
metrics, frame = run_episode(env, greedy, seed=0)
for key, value in metrics.items():
    print(f"  {key:20s} {value:.3f}" if isinstance(value, float) else f"  {key:20s} {value}")

fig, ax = plt.subplots(figsize=(10, 2.2))
ax.imshow(frame)
ax.set_axis_off()
ax.set_title("trained DIACC agent (green CAVs) among human drivers, step 30")
fig.savefig(OUT / "trained_agent_frame.png", dpi=120, bbox_inches="tight")
plt.close(fig)

# %% [markdown]
# ## Greedy, sampled, and lane keeping
#
# `load_policy(path, sampled=True)` draws each action from the policy's
# distribution instead of taking the most likely one; `policy.reset(seed)`
# seeds those draws, so a sampled episode is reproducible too. As a
# reference we let the same CAVs only ever answer `remain` (action 0): PSAR
# still keeps them safe, but they never choose a lane. Three seeds each, so
# this takes a few seconds; the numbers describe these three episodes only.

# %%
sampled_policy = diacc.load_policy(CHECKPOINT, sampled=True)
plain = policy.make_env()  # no rendering needed here


def sampled(observations):
    return sampled_policy.act(observations)


def remain(observations):
    return {agent: 0 for agent in observations}


rows = []
for label, choose, agent in (
    ("greedy", greedy, policy),
    ("sampled", sampled, sampled_policy),
    ("remain", remain, None),
):
    speeds, waits = [], []
    for seed in range(3):
        if agent is not None:
            agent.reset(seed=seed)
        episode, _ = run_episode(plain, choose, seed=seed)
        speeds.append(episode["mean_speed_mps"])
        waits.append(episode["p_we"])
    rows.append((label, sum(speeds) / 3, sum(waits) / 3))
print(f"{'CAVs':8s} {'mean speed':>12s} {'p(WE)':>8s}   (highway, train-50, seeds 0-2)")
for label, speed, wait in rows:
    print(f"{label:8s} {speed:9.2f} m/s {100 * wait:6.1f} %")
env.close()
plain.close()
