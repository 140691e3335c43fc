"""SUMO backend benchmark: our worker-process backend vs a raw libsumo loop.

Both sides run in the same invocation on the same generated network with the
same SUMO options, the same population (N = 25 HDVs, ``train-50``), the same
sub-stepping and the same libsumo calls a TrafficState needs
(:mod:`diacc.sim.backends.sumo.worker`): one subscription read of the worker's
``STATE_VARIABLES`` (lane, lane position, lateral offset, speed and angle) for
every vehicle per decision step (vehicles missing from it have arrived) and
the collision list after every sub-step. The population has no CAVs, so
neither side sends per-vehicle commands. Episodes restart when every vehicle
has left or after ``SimConfig.episode_steps``; restarts are timed on both
sides. The raw loop keeps SUMO's answers as they come, so the ratio (raw rate
/ backend rate) is the overhead of the worker process, the pipe (one round
trip per decision step) and building the TrafficState arrays; the target is
<= 2x.

K = 1 and K = 2 backends (``step_async`` / ``step_wait``, steps per second
summed over the K) and the raw loop run in turns of ``steps / ROUNDS``, so
that load changes during the run hit all three alike. Besides wall time the
table shows the CPU time per decision step of every process involved (this
one and the workers, from ``/proc``, so Linux only): on a loaded machine the
wall-time ratio also counts the waits for the scheduler to wake the worker
and then the caller at every step, which the raw loop never has; the CPU
ratio is what our code itself costs.

Run: ``diacc bench --backend sumo [--timing-steps N]`` or
``python -m diacc.experiments.bench.sumo``.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from diacc.config import SimConfig
from diacc.sim.backends.base import CavCommands
from diacc.sim.backends.sumo.backend import SumoBackend
from diacc.sim.backends.sumo.net import ROUTE_ID
from diacc.sim.backends.sumo.vtypes import HDV_TYPES
from diacc.sim.maps import load_map
from diacc.sim.scenario import Scenario, draw_population

MAP_NAME = "train-50"
N_VEHICLES = 25
#: Each measurement is split into this many chunks, run in turn with the other
#: measurements', so that a change of machine load hits all of them alike.
ROUNDS = 5


def _process_cpu_s(pid: int) -> float:
    """CPU seconds (user + system) a process has used so far, from ``/proc``.

    NaN without ``/proc`` (not Linux): the table then shows "nan" CPU figures.
    """
    if not Path("/proc/self/stat").exists():
        return float("nan")
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime


class _BackendLoop:
    """K backends stepped concurrently (``step_async`` / ``step_wait``) with idle commands."""

    def __init__(self, backends: list[SumoBackend], scenario: Scenario, seed: int) -> None:
        self.backends, self.scenario, self.seed = backends, scenario, seed
        self.idle = CavCommands.idle(scenario.n_vehicles)
        for k, b in enumerate(backends):
            b.reset(scenario, seed + k)
        self.age = 0

    def cpu_s(self) -> float:
        """CPU seconds of this process and the workers: the whole cost of the steps."""
        return time.process_time() + sum(_process_cpu_s(b.worker_pid) for b in self.backends)

    def advance(self, steps: int) -> None:
        for _ in range(steps):
            for b in self.backends:
                b.step_async(self.idle)
            states = [b.step_wait() for b in self.backends]
            self.age += 1
            for k, (b, st) in enumerate(zip(self.backends, states, strict=True)):
                if st.arrived.all() or self.age >= b.sim.episode_steps:
                    b.reset(self.scenario, self.seed + k)
            if self.age >= self.backends[0].sim.episode_steps:
                self.age = 0


class _RawLoop:
    """A plain libsumo loop in this process doing the backend's libsumo calls, nothing else."""

    def __init__(self, backend: SumoBackend, scenario: Scenario, seed: int) -> None:
        import libsumo
        import sumolib

        from diacc.sim.backends.sumo.worker import STATE_VARIABLES, SumoSim

        spec = backend._spec  # same network, vTypes and options as the backend's worker
        self.ls, self.args, self.sim = libsumo, SumoSim(spec)._args(seed), spec.sim
        self.pop = draw_population(scenario, spec.road, seed)
        self.lane0 = spec.road.first_lane(0)
        self.variables = [getattr(libsumo.constants, name) for name in STATE_VARIABLES]
        self.ids = [f"v{i}" for i in range(self.pop.n_vehicles)]
        libsumo.start([sumolib.checkBinary("sumo"), *self.args])
        self._insert()

    def _insert(self) -> None:
        pop, ls, length_m = self.pop, self.ls, self.sim.vehicle_length_m
        for i, vid in enumerate(self.ids):
            ls.vehicle.add(
                vid, ROUTE_ID, typeID=HDV_TYPES[pop.style[i]], depart="0",
                departLane=str(int(pop.lane[i]) - self.lane0),
                departPos=f"{pop.x_m[i] + 0.5 * length_m:.3f}",
                departSpeed=f"{pop.speed_mps[i]:.3f}",
            )  # fmt: skip
        ls.simulationStep()
        for vid in self.ids:
            ls.vehicle.subscribe(vid, self.variables)
        self.age = 0

    def cpu_s(self) -> float:
        return time.process_time()

    def advance(self, steps: int) -> None:
        ls, substeps, episode_steps = self.ls, self.sim.substeps, self.sim.episode_steps
        for _ in range(steps):
            for _ in range(substeps):
                ls.simulation.step()
                ls.simulation.getCollisions()
            on_road = ls.vehicle.getAllSubscriptionResults()
            self.age += 1
            if not on_road or self.age >= episode_steps:
                ls.load(self.args)
                self._insert()

    def close(self) -> None:
        self.ls.close()


def _measure(loops: list, steps: int) -> list[tuple[float, float]]:
    """(wall s, CPU s) per decision step of each loop, run in turns of ``steps / ROUNDS``."""
    wall, cpu = [0.0] * len(loops), [0.0] * len(loops)
    for r in range(ROUNDS):
        chunk = steps // ROUNDS + (r < steps % ROUNDS)
        for i, loop in enumerate(loops):
            cpu0, t0 = loop.cpu_s(), time.perf_counter()
            loop.advance(chunk)
            wall[i] += time.perf_counter() - t0
            cpu[i] += loop.cpu_s() - cpu0
    return [(w / steps, c / steps) for w, c in zip(wall, cpu, strict=True)]


def run(steps: int = 500, seed: int = 0) -> dict:
    """Measure and print backend vs raw libsumo rates and K = 1, 2 concurrent rates."""
    from rich.console import Console
    from rich.table import Table

    road, sim = load_map(MAP_NAME), SimConfig()
    scenario = Scenario(n_vehicles=N_VEHICLES, cav_penetration=0.0)
    backends = [SumoBackend(road, sim) for _ in range(3)]
    raw_loop = None
    try:
        version = backends[0].version
        raw_loop = _RawLoop(backends[0], scenario, seed)
        loops = [
            raw_loop,
            _BackendLoop(backends[:1], scenario, seed),
            _BackendLoop(backends[1:], scenario, seed),
        ]
        (raw_s, raw_cpu_s), (k1_s, k1_cpu_s), (k2_s, _) = _measure(loops, steps)
    finally:
        if raw_loop is not None:
            raw_loop.close()
        for b in backends:
            b.close()
    raw, k1, k2 = 1.0 / raw_s, 1.0 / k1_s, 2.0 / k2_s
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
        "raw_cpu_ms_per_step": 1e3 * raw_cpu_s,
        "backend_cpu_ms_per_step": 1e3 * k1_cpu_s,
        "cpu_overhead_ratio": k1_cpu_s / raw_cpu_s,
        "load_average_1min": os.getloadavg()[0],
    }
    load = result["load_average_1min"]
    table = Table(
        title=f"SUMO backend, {MAP_NAME}, N={N_VEHICLES}, {sim.substeps} substeps/step, "
        f"{version}, load {load:.1f} on {os.cpu_count()} CPUs"
    )
    table.add_column("measurement")
    table.add_column("decision steps/s", justify="right")
    table.add_column("CPU ms/step (all processes)", justify="right")
    table.add_row("raw libsumo loop (same calls)", f"{raw:.0f}", f"{1e3 * raw_cpu_s:.3f}")
    table.add_row("SumoBackend, K=1", f"{k1:.0f}", f"{1e3 * k1_cpu_s:.3f}")
    table.add_row("SumoBackend, K=2 concurrent (sum)", f"{k2:.0f}", "")
    table.add_row(
        "overhead ratio backend / raw", f"{raw / k1:.2f}x", f"{k1_cpu_s / raw_cpu_s:.2f}x"
    )
    Console().print(table)
    return result


if __name__ == "__main__":
    print(run())
