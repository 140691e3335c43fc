"""Speed of the ``highway`` backend against stock multi-agent ``highway-v0``, same run.

Both sides simulate 10 controlled vehicles among 15 IDM vehicles at a 1 Hz
decision rate with the same number of integration sub-steps per decision
(``simulation_frequency = substeps / step_s``) and receive seeded random
actions from the same distribution (:data:`ACTION_PROBS`); each side resets when
its own episode ends (ours: collision, all arrived or ``episode_steps``). Only
``step`` calls are timed (resets are not), on one core, in this process, back to
back, so machine load affects both alike. Our side builds no observation (that
is the environment's job); stock's step includes its Kinematics observation.

Run: ``python -m diacc.experiments.bench.highway``.
"""

from __future__ import annotations

import time

import numpy as np
from rich.console import Console
from rich.table import Table

from diacc.config import SimConfig
from diacc.sim.backends.base import CavCommands
from diacc.sim.backends.highway.backend import HighwayBackend
from diacc.sim.maps import load_map
from diacc.sim.scenario import Scenario

N_CAVS = 10


#: Action distribution of both sides: (remain, left, right, faster, slower), mostly
#: idle with random speed changes and occasional lane changes, so that neither
#: simulator spends the run resetting after crashes.
ACTION_PROBS = (0.5, 0.05, 0.05, 0.2, 0.2)
#: Our commands per action: (lane change, speed change in units of speed_change_mps).
_OUR_ACTIONS = np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1]])
#: The same actions in highway-env's DiscreteMetaAction order {0 LEFT, 1 IDLE, 2 RIGHT,
#: 3 FASTER, 4 SLOWER} (the orders differ: map explicitly).
_STOCK_ACTIONS = np.array([1, 0, 2, 3, 4])


def _random_commands(rng: np.random.Generator, n: int, speed_change_mps: float) -> CavCommands:
    """Seeded random CAV commands of one env drawn from :data:`ACTION_PROBS`, (1, V)."""
    action = rng.choice(5, size=n, p=ACTION_PROBS)
    lane, speed = _OUR_ACTIONS[action].T
    return CavCommands(
        lane.astype(np.int8)[None], speed.astype(np.float64)[None] * speed_change_mps
    )


def time_ours(
    steps: int, n_vehicles: int, n_cavs: int, seed: int, map_name: str = "train-25"
) -> float:
    """Environment steps per second of :class:`HighwayBackend` (step calls only)."""
    sim = SimConfig()
    backend = HighwayBackend(load_map(map_name), sim)
    scenario = Scenario.with_cavs(n_vehicles, n_cavs)
    rng = np.random.default_rng(seed)
    state = backend.reset(scenario, seed)
    episode, elapsed_s = 0, 0.0
    for _ in range(steps):
        commands = _random_commands(rng, n_vehicles, sim.speed_change_mps)
        t0 = time.perf_counter()
        state = backend.step(commands)
        elapsed_s += time.perf_counter() - t0
        if len(state.collisions) or not state.active.any() or state.step[0] >= sim.episode_steps:
            episode += 1
            state = backend.reset(scenario, seed + episode)
    backend.close()
    return steps / elapsed_s


def time_stock(steps: int, n_vehicles: int, n_cavs: int, seed: int) -> float:
    """Environment steps per second of stock multi-agent ``highway-v0`` (step calls only)."""
    import gymnasium as gym
    import highway_env  # noqa: F401  (registers the environments)

    sim = SimConfig()
    env = gym.make(
        "highway-v0",
        config={
            "controlled_vehicles": n_cavs,
            "vehicles_count": n_vehicles - n_cavs,
            "lanes_count": 4,
            "action": {
                "type": "MultiAgentAction",
                "action_config": {"type": "DiscreteMetaAction"},
            },
            "observation": {
                "type": "MultiAgentObservation",
                "observation_config": {"type": "Kinematics"},
            },
            "policy_frequency": round(1.0 / sim.step_s),
            "simulation_frequency": round(sim.substeps / sim.step_s),
            "duration": sim.episode_steps,
        },
    )
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    episode, elapsed_s = 0, 0.0
    for _ in range(steps):
        action = tuple(int(a) for a in _STOCK_ACTIONS[rng.choice(5, size=n_cavs, p=ACTION_PROBS)])
        t0 = time.perf_counter()
        _, _, terminated, truncated, _ = env.step(action)
        elapsed_s += time.perf_counter() - t0
        if terminated or truncated:
            episode += 1
            env.reset(seed=seed + episode)
    env.close()
    return steps / elapsed_s


def run(steps: int = 200, stock_steps: int = 20, n_vehicles: int = 25, seed: int = 0) -> dict:
    """Time both simulators in this process and print a table; return the figures.

    Returns:
        ``{"ours_steps_per_s", "stock_steps_per_s", "ratio", "ours_n40_steps_per_s",
        "n_vehicles", "steps", "stock_steps"}``.
    """
    n_cavs = min(N_CAVS, n_vehicles)
    stock = time_stock(stock_steps, n_vehicles, n_cavs, seed)
    ours = time_ours(steps, n_vehicles, n_cavs, seed)
    ours_40 = time_ours(steps, 40, N_CAVS, seed)
    result = {
        "ours_steps_per_s": ours,
        "stock_steps_per_s": stock,
        "ratio": ours / stock,
        "ours_n40_steps_per_s": ours_40,
        "n_vehicles": n_vehicles,
        "steps": steps,
        "stock_steps": stock_steps,
    }
    table = Table(title=f"highway backend vs stock highway-v0 ({n_cavs} controlled, 1 Hz)")
    table.add_column("simulator")
    table.add_column("vehicles", justify="right")
    table.add_column("timed steps", justify="right")
    table.add_column("env steps/s", justify="right")
    table.add_row(
        "stock highway-v0 (multi-agent)", str(n_vehicles), str(stock_steps), f"{stock:.1f}"
    )
    table.add_row("diacc highway backend", str(n_vehicles), str(steps), f"{ours:.0f}")
    table.add_row("diacc highway backend", "40", str(steps), f"{ours_40:.0f}")
    table.add_row("ratio (ours / stock)", str(n_vehicles), "", f"{ours / stock:.0f}x")
    Console().print(table)
    return result


if __name__ == "__main__":
    run()
