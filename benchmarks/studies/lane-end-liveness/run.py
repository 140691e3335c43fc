"""Liveness at lane ends (issue 44): do CAVs that merge at the last moment all get through?

100 % CAVs driven by the ``late-merge`` script (keep the lane until 150 m
before its end, then ask for the surviving side;
:class:`~diacc.experiments.policies.ScriptedPolicy`) under the default PSAR,
against pure human traffic of the same cell, on every shipped map and both
backends, ``realistic`` preset, 330-step episodes, seeds as ``diacc eval``'s.
Per row: the share of vehicles that never arrived, delay per vehicle
(s), collisions and the episodes in which some vehicle never arrived::

    python benchmarks/studies/lane-end-liveness/run.py --vehicles 25 50 --episodes 10

Run it on two source trees (``git worktree add /tmp/before REV``, then
``PYTHONPATH=/tmp/before python benchmarks/studies/lane-end-liveness/run.py ...``) for a
before / after table; results/late-merge-vs-pure-hdv.md holds the committed one.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from diacc.envs.episode import EpisodeDriver
from diacc.experiments.evaluate import run_episode
from diacc.experiments.grid import Cell
from diacc.experiments.policies import EvalSettings, PolicySpec, build_policy
from diacc.sim.maps import available_maps


def row(backend: str, map_name: str, n_vehicles: int, policy_name: str, episodes: int) -> str:
    policy = build_policy(PolicySpec(policy_name))
    rho = 0.0 if policy_name == "pure-hdv" else 1.0
    cell = Cell(map_name, n_vehicles, rho, "D1")
    driver = EpisodeDriver(policy, policy.env_config(cell, EvalSettings(backend, 330)))
    try:
        rows = [run_episode(driver, cell, k, "legacy").row for k in range(episodes)]
    finally:
        driver.close()
    stuck = [r["episode"] for r in rows if r["never_arrived_fraction"] > 0]
    return (
        f"| {backend} | {map_name} | {n_vehicles} | {policy_name} "
        f"| {np.mean([r['never_arrived_fraction'] for r in rows]):.1%} "
        f"| {np.mean([r['delay_per_vehicle_s'] for r in rows]):.1f} "
        f"| {sum(r['n_collisions'] for r in rows)} | {stuck or ''} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vehicles", type=int, nargs="+", default=[25, 50])
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--backends", nargs="+", default=["highway", "sumo"])
    parser.add_argument("--maps", nargs="+", default=None)
    parser.add_argument("--policies", nargs="+", default=["late-merge", "pure-hdv"])
    args = parser.parse_args()
    start = time.perf_counter()
    print(
        f"late merging at 100 % CAVs: {args.episodes} episodes per row, realistic preset, 330 steps"
    )
    print("| backend | map | N | policy | never arrived | delay s/veh | collisions | stuck in |")
    print("|---|---|---|---|---|---|---|---|")
    for backend in args.backends:
        for map_name in args.maps or available_maps():
            for n_vehicles in args.vehicles:
                for policy_name in args.policies:
                    print(
                        row(backend, map_name, n_vehicles, policy_name, args.episodes), flush=True
                    )
    print(f"({time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
