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
# # 6. Train a DIACC agent, watch it learn, evaluate it
#
# Training is MAPPO: all CAVs share one actor (D-IADM: the TAIE encoder of
# tutorial 3, a GRU and PSAR from tutorial 4), and a centralised critic
# (C-IEC) scores the whole road, trained on the team reward of tutorial 5.
# The command line does it all:
#
# ```bash
# diacc train --variant diacc --steps 4000 --envs 4 --out runs/quickstart
# diacc eval --policy runs/quickstart/checkpoint.pt --episodes 3 --out results/quickstart
# diacc eval --policy pure-hdv --episodes 3 --out results/pure-hdv
# diacc table results/pure-hdv results/quickstart
# ```
#
# Here we call the same functions from Python, with a run small enough for a
# laptop CPU in under a minute: a few PPO updates with small networks. Such a
# run does **not** learn to drive (the paper trains for 3 M steps); it shows
# the workflow. Set `DIACC_TUTORIAL_TRAIN_STEPS` to train longer.

# %%
import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import torch

from diacc import cli
from diacc.config import TrainConfig, override
from diacc.experiments.evaluate import evaluate, load_episodes
from diacc.experiments.grid import make_cell
from diacc.experiments.plots import plot_curves, plot_speeds, read_progress
from diacc.experiments.policies import EvalSettings, parse_policy
from diacc.learn.checkpoint import save_checkpoint
from diacc.learn.mappo import make_agent, seed_everything, train

OUT = Path(os.environ.get("DIACC_TUTORIAL_OUT", "tutorial_out")) / "06_train"
OUT.mkdir(parents=True, exist_ok=True)
TRAIN_STEPS = int(os.environ.get("DIACC_TUTORIAL_TRAIN_STEPS", "120"))

# %% [markdown]
# ## The training configuration
#
# `TrainConfig` holds every default (`diacc/config.py`): the paper's, but for
# a cheaper learner that measured at least as good per step (hidden sizes 64
# and 4 minibatches; `configs/paper-learner.toml` has the paper's 128 and 1).
# `override` changes fields by dotted name, exactly like
# `diacc train --set model.hidden_dim=32`. We shrink the run: one
# environment, 40-step rollouts (a multiple of the 10-step recurrent chunks:
# 4 sequences, one per minibatch), 2 PPO epochs per update instead of 5,
# smaller networks and 40-decision
# episodes (a rollout must hold whole episodes: every update restarts them).

# %%
run_dir = OUT / "run"
cfg = override(
    TrainConfig(),
    {
        "variant": "diacc",
        "env.backend": "highway",
        "env.map": "train-25",
        "total_steps": TRAIN_STEPS,  # environment steps = decisions x environments
        "n_envs": 1,
        "rollout_steps": 40,
        "epochs": 2,
        "checkpoint_every": 1,
        "seed": 1,
        "device": "cpu",
        "run_dir": str(run_dir),
        "model.hidden_dim": 32,
        "model.gru_hidden": 32,
        "model.cross_dim": 32,
        "model.cross_heads": 4,
        "model.gat_heads": 2,
        "env.sim.episode_steps": 40,
    },
)
print(
    f"{cfg.variant} on {cfg.env.backend}/{cfg.env.map}: {cfg.total_steps} steps, "
    f"{cfg.total_steps // (cfg.rollout_steps * cfg.n_envs)} PPO updates"
)

# %% [markdown]
# ## An untrained agent, for comparison
#
# `make_agent` builds the networks of a variant with their initial
# (orthogonal) weights; `save_checkpoint` writes them in the same format the
# trainer uses, so the evaluator can run the untrained actor too.

# %%
untrained_dir = OUT / "untrained_run"
untrained_dir.mkdir(parents=True, exist_ok=True)
seed_everything(cfg.seed)
untrained_ckpt = untrained_dir / "checkpoint.pt"
save_checkpoint(untrained_ckpt, make_agent(cfg, torch.device("cpu")), cfg, update=0, global_step=0)

# %% [markdown]
# ## Train
#
# `train` writes the run directory: `config.json`, `checkpoint.pt` (after
# every `checkpoint_every` updates), `progress.jsonl` (one line of metrics
# per update) and TensorBoard logs in `tb/`. A run that already finished in
# this folder is reused.

# %%
checkpoint = run_dir / "checkpoint.pt"
done = (
    checkpoint.exists()
    and (run_dir / "progress.jsonl").exists()
    and (read_progress(run_dir)["global_step"][1].max() >= cfg.total_steps)
)
if not done:  # overwrite: replace an unfinished run (without it, train refuses the folder)
    train(cfg, progress=False, overwrite=True)
print(sorted(p.name for p in run_dir.iterdir()))

# %% [markdown]
# ## Training curves
#
# `plot_curves` (or `diacc plot curves RUN_DIR`) draws the paper's three
# curves: collision rate, global reward and individual reward over
# environment steps. `read_progress` gives every logged series, e.g. the PPO
# diagnostics and the PSAR fire rates per CAV decision.

# %%
curve_files = plot_curves([run_dir], OUT / "curves")
print("wrote", *map(str, curve_files))

series = read_progress(run_dir)
panels = {
    "PPO losses": ("policy_loss", "value_loss"),
    "entropy / approx. KL": ("entropy", "approx_kl"),
    "PSAR fire rate per decision": (
        "psar/cancel_lc",
        "psar/decel_lc",
        "psar/force_brake",
        "psar/suppr_accel",
    ),
    "softmin temperature": ("tau",),
}
fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.5))
for ax, (title, keys) in zip(axes, panels.items(), strict=True):
    for key in keys:
        if key in series:
            steps, values = series[key]
            ax.plot(steps, values, marker="o", label=key)
    ax.set(title=title, xlabel="environment steps")
    ax.legend(fontsize=7)
fig.tight_layout()
diagnostics_png = OUT / "diagnostics.png"
fig.savefig(diagnostics_png, dpi=110)
plt.close(fig)
print("wrote", diagnostics_png)

# %% [markdown]
# ## Evaluate: trained vs untrained vs pure HDV traffic
#
# The evaluator runs seeded episodes on grid cells; every policy meets the
# same traffic draws (the seed depends on the cell and episode only). Here:
# one cell (the training cell of the paper), 2 episodes of 25 decisions per
# policy. `pure-hdv` is the baseline where every CAV is replaced by a human
# driver.

# %%
cell = make_cell({"map": "train-25", "n_vehicles": 25, "cav_penetration": 0.4, "style_mix": "D1"})
settings = EvalSettings(backend="highway", episode_steps=25)
policies = {
    "pure-hdv": parse_policy("pure-hdv"),
    "untrained": parse_policy(str(untrained_ckpt)),
    "trained": parse_policy(str(checkpoint)),
}
results = {}
for name, spec in policies.items():
    results[name] = OUT / "results" / name
    evaluate(spec, [cell], episodes=2, out_dir=results[name], settings=settings, progress=False)
    _, rows = load_episodes(results[name])
    print(
        f"{name:>10}: "
        + ", ".join(
            f"episode {r['episode']}: {float(r['mean_speed_mps']):.1f} m/s, "
            f"{r['steps']} steps, collision {r['collision']}"
            for r in rows
        )
    )

# %% [markdown]
# ## The paper-style table
#
# `diacc table` prints mean speed, p(WE) and p(SCE) per cell, one column per
# results directory, with the change relative to pure HDV traffic. We call the
# command-line entry point directly.

# %%
table_md = OUT / "table.md"
cli.main(["table", *map(str, results.values())])
cli.main(["table", *map(str, results.values()), "--out", str(table_md)])

speed_files = plot_speeds(list(results.values()), OUT / "speeds")
print("wrote", *map(str, speed_files))
