"""Where does a checkpoint crash? One line per colliding pair of a few episodes.

    python benchmarks/studies/paper-convergence/crash_probe.py RUN_DIR [EPISODES] \
        [--style-preset paper-congestion] [--backend sumo] \
        [--stream test --only 6,8,25 --episode-steps 330]

Plays ``validation`` episodes of the paper's training cell (``train-50``, N = 25,
rho = 0.4, D1, ``paper-congestion`` drivers unless told otherwise) with the
checkpoint, greedy, on highway (or ``--backend sumo``), and prints for every
collision the step, both vehicles (kind, lane, position along the route, speed) and
the segment, and each vehicle's lane, position and speed over the steps before
(``--history``, the oldest first; a collided vehicle is reported where it was at the
start of its crash step): what the 100 % collision rate of the variants without PSAR is made of
(docs/results/paper-convergence.md). ``--stream test --only 6,8,25`` replays the given
episodes of another stream: what the collisions an evaluation reported were (it plays
the same seeds as ``diacc eval``'s episodes of those numbers).
"""

from __future__ import annotations

import argparse
from collections import deque

import torch

from diacc.envs.episode import EpisodeDriver
from diacc.errors import DiaccError
from diacc.experiments.evalsettings import EvalSettings
from diacc.experiments.grid import Cell
from diacc.experiments.policies import build_policy, parse_policy


def describe(state, history, env: int, i: int) -> str:
    """One vehicle at the collision and over the steps before (a crash may zero its speed)."""
    kind = "CAV" if state.is_cav[env, i] else "HDV"
    path = ", ".join(
        f"{s.lane[env, i]}/{s.x_m[env, i]:.0f}/{s.speed_mps[env, i]:.1f}" for s in history
    )
    return (
        f"{kind} {i} (lane {state.lane[env, i]}, x {state.x_m[env, i]:.0f} m, "
        f"segment {state.segment[env, i]}; before, lane/x m/speed m/s: {path})"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", help="a training run's folder or a checkpoint.pt")
    parser.add_argument("episodes", nargs="?", type=int, default=4)
    parser.add_argument("--style-preset", default="paper-congestion")
    parser.add_argument("--backend", default="highway", choices=("highway", "sumo"))
    parser.add_argument("--stream", default="validation", choices=("validation", "test"))
    parser.add_argument("--episode-steps", type=int, help="as diacc eval's (else the run's)")
    parser.add_argument("--history", type=int, default=3, help="steps shown before a crash")
    parser.add_argument("--only", help="comma-separated episode numbers (else 0..EPISODES-1)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    policy = build_policy(parse_policy(args.run_dir))
    cell = Cell(map="train-50", n_vehicles=25, cav_penetration=0.4, style_mix="D1")
    settings = EvalSettings(
        style_preset=args.style_preset, backend=args.backend, episode_steps=args.episode_steps
    )
    driver = EpisodeDriver(policy, policy.env_config(cell, settings))
    chosen = [int(e) for e in args.only.split(",")] if args.only else range(args.episodes)
    for episode in chosen:
        driver_seed = cell.seed(episode, args.stream)
        history = deque([driver.reset(driver_seed)], maxlen=args.history)
        while not driver.done:
            state = driver.step()
            for env, i, j in state.collisions:
                print(
                    f"episode {episode} (seed {driver_seed}), step {driver.steps}: "
                    f"{describe(state, history, env, i)} with {describe(state, history, env, j)}"
                )
            history.append(state)  # each step's state is a new one
    driver.close()


if __name__ == "__main__":
    try:
        main()
    except DiaccError as error:  # an unknown run or preset: one line
        raise SystemExit(f"crash_probe.py: error: {error}") from None
