"""What does a checkpoint do? The share of each greedy action, one line per run.

    python benchmarks/studies/paper-convergence/action_probe.py RUN_DIR [RUN_DIR ...]

(a RUN_DIR may also be any policy `diacc eval --policy` takes, e.g. ``accelerate``).

Plays 4 ``validation`` episodes of the paper's training cell (``train-50``,
N = 25, rho = 0.4, D1, ``paper-congestion`` drivers) with each checkpoint,
greedy, on highway, and counts the action of every living CAV at every
decision. It is how a collapsed policy shows (docs/results/paper-convergence.md:
*lane right* on every decision), and what the learned skill is made of
(accelerate, with timed moves right).
"""

from __future__ import annotations

import sys

import numpy as np
import torch

from diacc.envs.actions import ACTION_NAMES
from diacc.envs.episode import EpisodeDriver
from diacc.errors import DiaccError
from diacc.experiments.evalsettings import EvalSettings
from diacc.experiments.grid import Cell
from diacc.experiments.policies import build_policy, parse_policy

EPISODES = 4


def action_shares(run_dir: str) -> np.ndarray:
    """(A,) share of each action over the living CAVs' decisions of the probe's episodes."""
    policy = build_policy(parse_policy(run_dir))
    counts = np.zeros(len(ACTION_NAMES), np.int64)  # (A,)
    cell = Cell(map="train-50", n_vehicles=25, cav_penetration=0.4, style_mix="D1")
    settings = EvalSettings(style_preset="paper-congestion")
    driver = EpisodeDriver(policy, policy.env_config(cell, settings))
    for episode in range(EPISODES):
        driver.reset(cell.seed(episode, "validation"))
        while not driver.done:
            driver.step()
        counts += driver.picked  # the policy's actions for living CAVs, before PSAR
    driver.close()
    return counts / max(counts.sum(), 1)


def main() -> None:
    torch.set_num_threads(1)
    if len(sys.argv) < 2:
        sys.exit("usage: action_probe.py RUN_DIR [RUN_DIR ...]")
    for run_dir in sys.argv[1:]:
        try:
            shares = action_shares(run_dir)
        except DiaccError as error:  # no checkpoint there, or an unusable one: one line
            raise SystemExit(f"action_probe.py: error: {error}") from None
        pairs = zip(ACTION_NAMES, shares, strict=True)
        text = ", ".join(f"{name} {share:.0%}" for name, share in pairs)
        print(f"{run_dir.rstrip('/').split('/')[-1]}: {text}")


if __name__ == "__main__":
    main()
