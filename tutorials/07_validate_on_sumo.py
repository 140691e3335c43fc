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
# # 7. Validate the trained agent on SUMO
#
# DIACC trains on the fast `highway` backend and validates on SUMO: the same
# map becomes a SUMO network (built with `netconvert`), the same population is
# inserted, and the CAVs are driven directly by the policy (SUMO's own safety
# checks off, so PSAR carries safety, as in the paper). A policy that only
# works on the simulator it was trained on would show it here.
#
# Equivalent commands:
#
# ```bash
# diacc eval --policy RUN_DIR/checkpoint.pt --backend sumo --episodes 3 --out results/sumo
# diacc eval --policy pure-hdv --backend sumo --episodes 3 --out results/sumo-hdv
# diacc table results/sumo-hdv results/sumo
# diacc render --policy RUN_DIR/checkpoint.pt --backend sumo --out episode.gif
# ```
#
# This tutorial reuses the checkpoint of tutorial 6 when it finds one in the
# same output folder; otherwise it trains a tiny one first.

# %%
import os
from pathlib import Path

import imageio.v2 as imageio
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from diacc import cli
from diacc.config import TrainConfig, override
from diacc.console import fmt
from diacc.experiments.evaluate import evaluate, load_episodes
from diacc.experiments.grid import make_cell
from diacc.experiments.plots import plot_speeds
from diacc.experiments.policies import EvalSettings, parse_policy
from diacc.experiments.render import render_episode
from diacc.learn.mappo import train

ROOT = Path(os.environ.get("DIACC_TUTORIAL_OUT", "tutorial_out"))
OUT = ROOT / "07_validate_on_sumo"
OUT.mkdir(parents=True, exist_ok=True)

# %% [markdown]
# ## The checkpoint
#
# A checkpoint stores the networks *and* the full training configuration, so
# the evaluator rebuilds the same observation layout, PSAR thresholds and
# network sizes from it.

# %%
checkpoint = ROOT / "06_train" / "run" / "checkpoint.pt"
if checkpoint.exists():
    print("reusing the checkpoint of tutorial 6:", checkpoint)
else:
    run_dir = OUT / "run"
    cfg = override(
        TrainConfig(),
        {
            "variant": "diacc",
            "env.backend": "highway",
            "env.map": "train-25",
            "total_steps": 40,
            "n_envs": 1,
            "rollout_steps": 40,
            "checkpoint_every": 1,
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
    checkpoint = run_dir / "checkpoint.pt"
    if not checkpoint.exists():
        train(cfg, progress=False, overwrite=True)
    print("trained a tiny agent:", checkpoint)
spec = parse_policy(str(checkpoint))

# %% [markdown]
# ## Evaluate on SUMO and on highway
#
# `EvalSettings(backend="sumo")` runs the cell on SUMO. We evaluate the agent on
# both simulators and the pure-HDV baseline on SUMO, 1 episode of 25
# decisions each (the paper uses many more), on the 50 % reduction map.

# %%
cell = make_cell({"map": "train-50", "n_vehicles": 25, "cav_penetration": 0.4, "style_mix": "D1"})
runs = {
    "sumo-hdv": (parse_policy("pure-hdv"), "sumo"),
    "sumo-diacc": (spec, "sumo"),
    "highway-diacc": (spec, "highway"),
}
results = {}
for name, (policy_spec, backend) in runs.items():
    results[name] = OUT / "results" / name
    settings = EvalSettings(backend=backend, episode_steps=25)
    evaluate(
        policy_spec, [cell], episodes=1, out_dir=results[name], settings=settings, progress=False
    )
    meta, rows = load_episodes(results[name])
    row = rows[0]
    version = f" ({row['sumo_version']})" if row["sumo_version"] else ""
    # the CSV holds nan where a value does not apply (no PSAR for pure HDV): say "n/a"
    force_brake = fmt(float(row["psar_force_brake_rate"]), 1, percent=True)
    print(
        f"{name:>14} on {meta['backend']}{version}: mean speed "
        f"{fmt(float(row['mean_speed_mps']), 1, 'm/s')}, {row['steps']} steps, "
        f"{'a collision' if row['collision'] == '1' else 'no collision'}, "
        f"PSAR force-brake rate {force_brake}"
    )

# %%
cli.main(["table", *map(str, results.values())])
speed_files = plot_speeds(list(results.values()), OUT / "speeds")
print("wrote", *map(str, speed_files))

# %% [markdown]
# ## An episode on SUMO as a GIF
#
# `render_episode` replays one seeded episode (by default the first one the
# evaluator ran in this cell) and draws every decision step with the same
# renderer as the `highway` backend: CAVs green, HDVs by style, and CAVs whose
# action PSAR changed in that step outlined in magenta.

# %%
gif = OUT / "sumo_episode.gif"
result = render_episode(spec, cell, gif, steps=25, settings=EvalSettings(backend="sumo"), fps=5.0)
print(
    f"wrote {result.path}: {result.n_frames} frames of {result.frame_shape}, "
    f"PSAR visible in {result.psar_frames}"
)

# The last frame as a PNG, to look at without a GIF viewer.
frames = imageio.mimread(gif)
last_png = OUT / "sumo_last_frame.png"
plt.imsave(last_png, frames[-1][..., :3])
print("wrote", last_png)
