"""Environment stepping per core: E envs on their own simulators vs one batched simulator.

What the trainer's rollout pays per env-step apart from the networks: the
simulator, PSAR, the observations, the reward and the episode recorder,
i.e. :meth:`VectorEnv.step` of the vector env with seeded random actions. Each
row times ``E`` environments for the same number of vector steps, first as
:class:`~diacc.envs.vector.SyncVectorEnv` (every env its own simulator, stepped
one after another) and then as :class:`~diacc.envs.vector.BatchedVectorEnv` (one
batched ``highway`` simulator for all E envs); both run the one step function
of :mod:`diacc.envs.batch`, so PSAR, observations and rewards are batched in
both and the difference is the simulator's. A second pair of columns times the
simulator alone (:meth:`HighwayBackend.step` of E backends vs one
:meth:`HighwayBackend.step` of one backend of E envs). One process, one thread: the figures are
per core. Automatic resets are included (short episodes make them frequent,
as in training), the start-up is not. ``benchmarks/speed/step_before_after.py``
compares the stepping of two source trees.

``python -m diacc.experiments.bench.envbatch --envs 1 4 16``; ``diacc bench --env-batch``.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
from rich.console import Console
from rich.table import Table

from diacc.config import EnvConfig, SimConfig, resolve_road
from diacc.envs.vector import make_vector_env
from diacc.sim.backends.base import CavCommands
from diacc.sim.backends.highway.backend import HighwayBackend

#: Actions of the timed steps: mostly keep lane with speed changes, as PSAR-filtered
#: policies do (the same distribution as :data:`diacc.experiments.bench.highway.ACTION_PROBS`).
ACTION_PROBS = (0.5, 0.05, 0.05, 0.2, 0.2)


def time_vector(config: EnvConfig, n_envs: int, mode: str, steps: int, seed: int) -> float:
    """Env-steps/s of ``steps`` vector steps of ``n_envs`` envs in vector ``mode``."""
    envs = make_vector_env(config, n_envs, seed, mode)
    rng = np.random.default_rng(seed)
    actions = rng.choice(5, size=(steps + 1, n_envs, envs.n_cavs), p=ACTION_PROBS)
    try:
        envs.reset(first_episode=0)
        envs.step(actions[0])  # warm-up: first-call costs are not the steady state
        start = time.perf_counter()
        for a in actions[1:]:
            envs.step(a)
        seconds = time.perf_counter() - start
    finally:
        envs.close()
    return n_envs * steps / seconds


def time_simulator(config: EnvConfig, n_envs: int, batched: bool, steps: int, seed: int) -> float:
    """Env-steps/s of the ``highway`` simulator alone: E backends, or one batch of E."""
    sim: SimConfig = config.sim
    road = resolve_road(config)
    backends = (
        [HighwayBackend(road, sim, n_envs=n_envs)]
        if batched
        else [HighwayBackend(road, sim) for _ in range(n_envs)]
    )
    rng = np.random.default_rng(seed)
    n = config.scenario.n_vehicles
    lane = rng.integers(-1, 2, (steps, n_envs, n)).astype(np.int8) * (
        rng.random((steps, n_envs, n)) < 0.1
    )
    speed = rng.normal(0.0, sim.speed_change_mps, (steps, n_envs, n))
    episodes = 0

    def reset(b: HighwayBackend, e: int) -> None:
        nonlocal episodes
        episodes += 1
        b.reset(config.scenario, seed + episodes, env=e)

    for b in backends:
        for e in range(b.n_envs):
            reset(b, e)
    seconds = 0.0
    for t in range(steps):
        start = time.perf_counter()
        if batched:
            states = [backends[0].step(CavCommands(lane[t], speed[t]))]
        else:
            commands = CavCommands(lane[t], speed[t])
            states = [b.step(commands.env(e)) for e, b in enumerate(backends)]
        seconds += time.perf_counter() - start
        # Resets are not timed: the env's own cost. One flag per env of the E = 1 or E batches.
        ended = np.concatenate(
            [
                np.isin(np.arange(s.n_envs), s.collisions[:, 0])
                | ~s.active.any(axis=1)
                | (s.step >= sim.episode_steps)
                for s in states
            ]
        )
        for e in np.flatnonzero(ended):
            b = backends[0] if batched else backends[e]
            reset(b, int(e) if batched else 0)
    return n_envs * steps / seconds


def run(envs: tuple[int, ...] = (1, 4, 16), steps: int = 60, seed: int = 0) -> list[dict]:
    """Time every env count both ways; print one table and return its rows."""
    config = EnvConfig()
    rows = []
    for n_envs in envs:
        sync = time_vector(config, n_envs, "sync", steps, seed)
        batched = time_vector(config, n_envs, "batched", steps, seed)
        sim_alone = time_simulator(config, n_envs, False, steps, seed)
        sim_batched = time_simulator(config, n_envs, True, steps, seed)
        rows.append(
            {
                "envs": n_envs,
                "env_sync_steps_per_s": sync,
                "env_batched_steps_per_s": batched,
                "sim_sync_steps_per_s": sim_alone,
                "sim_batched_steps_per_s": sim_batched,
            }
        )
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    table = Table(
        title=f"env-steps/s per core: {config.scenario.n_vehicles} vehicles, "
        f"{config.scenario.n_cavs} CAVs, {steps} timed vector steps; "
        f"{os.cpu_count()} cores, load average {load}"
    )
    for col in (
        "envs",
        "env step: own simulators",
        "env step: batched simulator",
        "ratio",
        "simulator: one after another",
        "simulator: batched",
        "ratio",
    ):
        table.add_column(col, justify="right")
    for r in rows:
        table.add_row(
            str(r["envs"]),
            f"{r['env_sync_steps_per_s']:.0f}",
            f"{r['env_batched_steps_per_s']:.0f}",
            f"x{r['env_batched_steps_per_s'] / r['env_sync_steps_per_s']:.2f}",
            f"{r['sim_sync_steps_per_s']:.0f}",
            f"{r['sim_batched_steps_per_s']:.0f}",
            f"x{r['sim_batched_steps_per_s'] / r['sim_sync_steps_per_s']:.2f}",
        )
    Console(width=160).print(table)
    print(
        "env step = simulator + PSAR + observations + reward + episode recorder "
        "(SyncVectorEnv vs BatchedVectorEnv: PSAR and the rest batched in both); "
        "simulator = HighwayBackend.step of E backends one after another vs one of E envs"
    )
    return rows


def build_parser() -> argparse.ArgumentParser:
    """``python -m diacc.experiments.bench.envbatch``'s options."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--envs", type=int, nargs="+", default=[1, 4, 16])
    p.add_argument(
        "--timing-steps", type=int, default=60, help="timed vector steps per row (default 60)"
    )
    # its former name, hidden (as in 'diacc bench --env-batch'); old command lines still run
    p.add_argument(
        "--steps", dest="timing_steps", type=int, default=argparse.SUPPRESS, help=argparse.SUPPRESS
    )
    return p


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    run(tuple(args.envs), args.timing_steps)


if __name__ == "__main__":
    main()
