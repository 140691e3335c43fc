"""Where does a checkpoint crash? One line per colliding pair of a few episodes.

    python benchmarks/studies/paper-convergence/crash_probe.py RUN_DIR [EPISODES]

Plays ``validation`` episodes of the paper's training cell (``train-50``, N = 25,
rho = 0.4, D1, ``paper-congestion`` drivers) with the checkpoint, greedy, on
highway, and prints for every collision the step, both vehicles (kind, lane,
position along the route, speed) and the segment: what the 100 % collision
rate of the variants without PSAR is made of (docs/results/paper-convergence.md).
"""

from __future__ import annotations

import sys

import torch

from diacc.envs.episode import EpisodeDriver
from diacc.experiments.evalsettings import EvalSettings
from diacc.experiments.grid import Cell
from diacc.experiments.policies import build_policy, parse_policy


def describe(state, env: int, i: int) -> str:
    kind = "CAV" if state.is_cav[env, i] else "HDV"
    return (
        f"{kind} {i} (lane {state.lane[env, i]}, x {state.x_m[env, i]:.0f} m, "
        f"{state.speed_mps[env, i]:.1f} m/s, segment {state.segment[env, i]})"
    )


def main() -> None:
    torch.set_num_threads(1)
    run_dir, episodes = sys.argv[1], int(sys.argv[2]) if len(sys.argv) > 2 else 4
    policy = build_policy(parse_policy(run_dir))
    cell = Cell(map="train-50", n_vehicles=25, cav_penetration=0.4, style_mix="D1")
    settings = EvalSettings(style_preset="paper-congestion")
    driver = EpisodeDriver(policy, policy.env_config(cell, settings))
    for episode in range(episodes):
        driver.reset(cell.seed(episode, "validation"))
        while not driver.done:
            state = driver.step()
            for env, i, j in state.collisions:
                print(
                    f"episode {episode}, step {driver.steps}: {describe(state, env, i)} "
                    f"with {describe(state, env, j)}"
                )
    driver.close()


if __name__ == "__main__":
    main()
