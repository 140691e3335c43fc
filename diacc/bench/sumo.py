"""SUMO backend benchmark: our worker-process backend vs a raw libsumo loop.

Both sides run in the same invocation on the same generated network with the
same SUMO options, the same population (N = 25 HDVs, ``train-50``), the same
sub-stepping and the same libsumo calls a TrafficState needs
(:mod:`diacc.backends.sumo.worker`): one subscription read of the worker's
``STATE_VARIABLES`` (lane, lane position, lateral offset, speed and angle) for
every vehicle per decision step (vehicles missing from it have arrived) and
the collision list after every sub-step. Episodes restart when every vehicle has left or after
``SimConfig.episode_steps``; restarts are timed on both sides. The raw loop
keeps SUMO's answers as they come, so the ratio (raw rate / backend rate) is
the overhead of the worker process, the pipe (one round trip per decision
step) and building the TrafficState arrays; the target is <= 2x. The
population has no CAVs, so neither side sends per-vehicle commands. The ratio
grows with the machine's load: each backend step waits twice for the
scheduler to wake a process, the raw loop never.

Then K = 1 and K = 2 backends step concurrently (``step_async`` /
``step_wait``), reporting environment steps per second summed over the K.

Run: ``python -m diacc.bench.sumo`` (or ``diacc bench`` if wired there).
"""

from __future__ import annotations

import time

from diacc.backends.base import CavCommands
from diacc.backends.sumo.backend import SumoBackend
from diacc.backends.sumo.net import ROUTE_ID
from diacc.backends.sumo.vtypes import HDV_TYPES
from diacc.config import SimConfig
from diacc.maps import load_map
from diacc.scenario import Scenario, draw_population

MAP_NAME = "train-50"
N_VEHICLES = 25


def _backend_rate(backends: list[SumoBackend], scenario: Scenario, steps: int, seed: int) -> float:
    """Environment steps per second summed over ``backends`` stepping concurrently."""
    idle = CavCommands.idle(scenario.n_vehicles)
    for k, b in enumerate(backends):
        b.reset(scenario, seed + k)
    age = 0
    start = time.perf_counter()
    for _ in range(steps):
        for b in backends:
            b.step_async(idle)
        states = [b.step_wait() for b in backends]
        age += 1
        for k, (b, st) in enumerate(zip(backends, states, strict=True)):
            if st.arrived.all() or age >= b.sim.episode_steps:
                b.reset(scenario, seed + k)
        if age >= backends[0].sim.episode_steps:
            age = 0
    return len(backends) * steps / (time.perf_counter() - start)


def _raw_rate(backend: SumoBackend, scenario: Scenario, steps: int, seed: int) -> float:
    """Decision steps per second of a plain libsumo loop in this process, same work."""
    import libsumo
    import sumolib

    from diacc.backends.sumo.worker import STATE_VARIABLES, SumoSim

    spec = backend._spec  # same network, vTypes and options as the backend's worker
    args = SumoSim(spec)._args(seed)
    sim: SimConfig = spec.sim
    pop = draw_population(scenario, spec.road, seed)
    variables = [getattr(libsumo.constants, name) for name in STATE_VARIABLES]
    ids = [f"v{i}" for i in range(pop.n_vehicles)]

    def reset(first: bool) -> None:
        if first:
            libsumo.start([sumolib.checkBinary("sumo"), *args])
        else:
            libsumo.load(args)
        for i, vid in enumerate(ids):
            libsumo.vehicle.add(
                vid, ROUTE_ID, typeID=HDV_TYPES[pop.style[i]], depart="0",
                departLane=str(int(pop.lane[i]) - spec.road.first_lane(0)),
                departPos=f"{pop.x_m[i] + 0.5 * sim.vehicle_length_m:.3f}",
                departSpeed=f"{pop.speed_mps[i]:.3f}",
            )  # fmt: skip
        libsumo.simulationStep()
        for vid in ids:
            libsumo.vehicle.subscribe(vid, variables)

    reset(first=True)
    try:
        age = 0
        start = time.perf_counter()
        for _ in range(steps):
            for _ in range(sim.substeps):
                libsumo.simulation.step()
                libsumo.simulation.getCollisions()
            on_road = libsumo.vehicle.getAllSubscriptionResults()
            age += 1
            if not on_road or age >= sim.episode_steps:
                reset(first=False)
                age = 0
        return steps / (time.perf_counter() - start)
    finally:
        libsumo.close()


def run(steps: int = 500, seed: int = 0) -> dict:
    """Measure and print backend vs raw libsumo rates and K = 1, 2 concurrent rates."""
    from rich.console import Console
    from rich.table import Table

    road, sim = load_map(MAP_NAME), SimConfig()
    scenario = Scenario(n_vehicles=N_VEHICLES, cav_penetration=0.0)
    backends = [SumoBackend(road, sim), SumoBackend(road, sim)]
    try:
        version = backends[0].version
        raw = _raw_rate(backends[0], scenario, steps, seed)
        k1 = _backend_rate(backends[:1], scenario, steps, seed)
        k2 = _backend_rate(backends, scenario, steps, seed)
    finally:
        for b in backends:
            b.close()
    result = {
        "sumo_version": version,
        "map": MAP_NAME,
        "n_vehicles": N_VEHICLES,
        "substeps": sim.substeps,
        "steps": steps,
        "raw_libsumo_steps_per_s": raw,
        "backend_steps_per_s": k1,
        "overhead_ratio": raw / k1,
        "k1_env_steps_per_s": k1,
        "k2_env_steps_per_s": k2,
    }
    table = Table(title=f"SUMO backend, {MAP_NAME}, N={N_VEHICLES}, {sim.substeps} substeps/step, "
                        f"{version}")  # fmt: skip
    table.add_column("measurement")
    table.add_column("decision steps/s", justify="right")
    table.add_row("raw libsumo loop (same getters)", f"{raw:.0f}")
    table.add_row("SumoBackend, K=1", f"{k1:.0f}")
    table.add_row("SumoBackend, K=2 concurrent (sum)", f"{k2:.0f}")
    table.add_row("overhead ratio raw / backend", f"{raw / k1:.2f}x")
    Console().print(table)
    return result


if __name__ == "__main__":
    print(run())
