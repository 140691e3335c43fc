"""Liveness at lane ends (issue 44): CAVs that keep their lane to its end all get through.

The ``late-merge`` script (:class:`~diacc.experiments.policies.ScriptedPolicy`)
keeps its lane until 150 m before the lane end and then asks for the surviving
side, so with 100 % CAVs every CAV of an ending lane queues at its end and gets
through only if PSAR lets it in (the zipper rule, docs/concepts/psar.md). Every
vehicle must arrive, without a collision, on both backends and every shipped
map. Before the fix, SUMO left CAVs at the end of train-50's and test-50's
ending lanes for good (20 vehicles: 4 of 4 episodes on train-50).
"""

from __future__ import annotations

import pytest

from diacc.envs.episode import EpisodeDriver
from diacc.experiments.evaluate import run_episode
from diacc.experiments.grid import Cell
from diacc.experiments.policies import EvalSettings, ScriptedPolicy
from diacc.sim.maps import available_maps


def every_vehicle_arrives(backend: str, map_name: str, n_vehicles: int, episodes: int) -> None:
    """Play ``episodes`` seeded episodes (seeds as ``diacc eval``'s) and check each one."""
    steps = 330  # an episode ends early once every vehicle has left
    policy = ScriptedPolicy("late-merge")
    cell = Cell(map_name, n_vehicles, 1.0, "D1")
    driver = EpisodeDriver(policy, policy.env_config(cell, EvalSettings(backend, steps)))
    try:
        for episode in range(episodes):
            row = run_episode(driver, cell, episode).row
            where = f"{backend} {map_name} N = {n_vehicles} episode {episode}"
            assert row["n_collisions"] == 0, f"{where}: collision"
            assert row["arrived_fraction"] == 1.0, (
                f"{where}: {row['never_arrived_fraction']:.0%} of the vehicles never arrived"
            )
            assert row["steps"] < steps, where
    finally:
        driver.close()


@pytest.mark.parametrize("map_name", available_maps())
@pytest.mark.parametrize("backend", ["highway", "sumo"])
def test_every_late_merging_cav_arrives(backend, map_name):
    every_vehicle_arrives(backend, map_name, n_vehicles=20, episodes=2)


@pytest.mark.slow
@pytest.mark.parametrize("map_name", available_maps())
@pytest.mark.parametrize("backend", ["highway", "sumo"])
def test_every_late_merging_cav_arrives_in_dense_traffic(backend, map_name):
    every_vehicle_arrives(backend, map_name, n_vehicles=50, episodes=10)
