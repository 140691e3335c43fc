"""Where does a checkpoint crash? One line per colliding pair of a few episodes.

    python benchmarks/studies/paper-convergence/crash_probe.py RUN_DIR [EPISODES] \
        [--style-preset paper-congestion] [--backend sumo]

Plays ``validation`` episodes of the paper's training cell (``train-50``, N = 25,
rho = 0.4, D1, ``paper-congestion`` drivers unless told otherwise) with the
checkpoint, greedy, on highway (or ``--backend sumo``), and prints for every
collision the step, both vehicles (kind, lane, position along the route, speed) and
the segment: what the 100 % collision rate of the variants without PSAR is made of
(docs/results/paper-convergence.md).
"""

from __future__ import annotations

import argparse

import torch

from diacc.envs.episode import EpisodeDriver
from diacc.errors import DiaccError
from diacc.experiments.evalsettings import EvalSettings
from diacc.experiments.grid import Cell
from diacc.experiments.policies import build_policy, parse_policy


def describe(state, before, env: int, i: int) -> str:
    """One vehicle at the collision; its speed a step before (a crash sets it to 0)."""
    kind = "CAV" if state.is_cav[env, i] else "HDV"
    return (
        f"{kind} {i} (lane {state.lane[env, i]}, x {state.x_m[env, i]:.0f} m, "
        f"a step before: lane {before.lane[env, i]}, x {before.x_m[env, i]:.0f} m, "
        f"{before.speed_mps[env, i]:.1f} m/s; segment {state.segment[env, i]})"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", help="a training run's folder or a checkpoint.pt")
    parser.add_argument("episodes", nargs="?", type=int, default=4)
    parser.add_argument("--style-preset", default="paper-congestion")
    parser.add_argument("--backend", default="highway", choices=("highway", "sumo"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    policy = build_policy(parse_policy(args.run_dir))
    cell = Cell(map="train-50", n_vehicles=25, cav_penetration=0.4, style_mix="D1")
    settings = EvalSettings(style_preset=args.style_preset, backend=args.backend)
    driver = EpisodeDriver(policy, policy.env_config(cell, settings))
    for episode in range(args.episodes):
        state = driver.reset(cell.seed(episode, "validation"))
        while not driver.done:
            before, state = state, driver.step()
            for env, i, j in state.collisions:
                print(
                    f"episode {episode}, step {driver.steps}: {describe(state, before, env, i)} "
                    f"with {describe(state, before, env, j)}"
                )
    driver.close()


if __name__ == "__main__":
    try:
        main()
    except DiaccError as error:  # an unknown run or preset: one line
        raise SystemExit(f"crash_probe.py: error: {error}") from None
