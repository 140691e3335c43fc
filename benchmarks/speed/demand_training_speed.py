"""Demand rollout and training speed: the on-road window against stepping every vehicle.

A demand episode holds every vehicle of the episode (480 at 3600 veh/h for
480 s) while a few dozen to ~150 are on the road. ``windowed`` is the code as it is:
the highway backend steps the vehicles not settled
(``HighwayBackend._window``), the neighbour search and safety events look at
the on-road window (``diacc.sim.state.on_road_window``), the critic holds the
on-road vehicles first (so ``obs.max_vehicles`` bounds those on the road) and
the GAT gathers for graphs over 64 nodes. ``full`` turns all of it off, which
is the code before the window (same results, ``tests/test_highway_window.py``
and ``tests/test_demand_window.py``): every vehicle stepped and searched, the
critic padded to all N. Each mode runs in its own process, one after the
other, and the machine's load average is printed with each. Rates are per
second of wall time and per second of the process's CPU time: on a machine
shared with other runs (nice 10) the second is the code's own cost.

The rollout steps ``--envs`` envs with random actions; the training is
``--train-envs`` envs, one 600-step rollout per update, the default learner
but for ``--minibatches``: the full critic's dense GAT over 480 nodes needs
about 4 GB per attention tensor at the default 4 minibatches (measured: a
run passed 10 GB and was stopped), so both modes learn in 24 smaller ones.
``--train-modes`` picks the modes that train (by default the windowed one
alone: a full-mode update is too slow for a shared 2-core machine)::

    python benchmarks/speed/demand_training_speed.py --rollout-steps 50 --updates 1
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from tempfile import TemporaryDirectory

MODES = ("full", "windowed")
KINDS = ("rollout", "train")  # what is timed


def config(args: argparse.Namespace, mode: str, run_dir: str):
    """The demand training config of the benchmark (``--train-envs``, 600-step episodes)."""
    from diacc.config import TrainConfig, override
    from diacc.sim.scenario import Scenario

    scenario = Scenario(
        kind="demand",
        inflow_vph=args.inflow,
        demand_s=args.demand_s,
        warmup_s=args.warmup_s,
        cav_penetration=0.4,
        cav_slots=16,  # the measured setting (the default until "every")
    )
    # Full: the critic pads to every vehicle of the episode; windowed: to those on the road.
    max_vehicles = scenario.n_vehicles if mode == "full" else args.max_on_road
    cfg = override(
        TrainConfig(),
        {"n_envs": args.train_envs, "rollout_steps": args.episode_steps, "device": "cpu",
         "minibatches": args.minibatches, "env.backend": "highway",
         "total_steps": max(args.updates, 1) * args.train_envs * args.episode_steps,
         "env.sim.episode_steps": args.episode_steps, "env.sim.style_preset": "zipper",
         "env.obs.max_vehicles": max_vehicles, "run_dir": run_dir},
    )  # fmt: skip
    return override(cfg, {"env.scenario": scenario})


def switch_window_off() -> None:
    """Every vehicle stepped, searched and given a critic row: the code before the window."""
    import diacc.envs.batch
    import diacc.envs.observation.frames
    import diacc.envs.safety
    import diacc.learn.models.gat
    from diacc.sim.backends.highway.backend import HighwayBackend

    def every_vehicle(active):
        return 0, active.shape[-1]

    class FullCritic(diacc.envs.observation.ObservationBuilder):
        def __init__(self, road, cfg, episode_steps, compact_critic=False):
            super().__init__(road, cfg, episode_steps, compact_critic=False)

    HighwayBackend.windowed = False
    diacc.envs.observation.frames.on_road_window = every_vehicle
    diacc.envs.safety.on_road_window = every_vehicle
    diacc.envs.batch.ObservationBuilder = FullCritic  # where the step builds its builder
    diacc.learn.models.gat.DENSE_MAX_NODES = 10**9


def rates(env_steps: int, start: tuple[float, float]) -> tuple[float, float]:
    """Env-steps per wall second and per CPU second since ``start`` (wall, CPU)."""
    return (
        env_steps / (time.perf_counter() - start[0]),
        env_steps / (time.process_time() - start[1]),
    )


def measure(args: argparse.Namespace, mode: str) -> dict:
    """Env-steps/s of a rollout (random actions) and of a training run, in this process."""
    import numpy as np

    from diacc.envs.vector import make_vector_env
    from diacc.learn.mappo import train

    if mode == "full":
        switch_window_off()
    out = {"mode": mode, "load_before": os.getloadavg()}
    with TemporaryDirectory() as tmp:
        cfg = config(args, mode, str(Path(tmp) / "run"))
        venv = make_vector_env(cfg.env, args.envs, run_seed=0)
        rng = np.random.default_rng(0)
        n_cavs = venv.reset()[0].alive.shape[-1]
        start, on_road = (time.perf_counter(), time.process_time()), 0
        for _ in range(args.rollout_steps):
            step = venv.step(rng.integers(0, 5, (args.envs, n_cavs)))
            on_road = max(on_road, int(step.critic_state.node_mask.sum(axis=-1).max()))
        out["rollout"] = rates(args.envs * args.rollout_steps, start)
        out["max_on_road"] = on_road
        venv.close()
        if args.updates and mode in args.train_modes:
            start = (time.perf_counter(), time.process_time())
            train(cfg, progress=False)
            out["train"] = rates(cfg.total_steps, start)
    out["load_after"] = os.getloadavg()
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--envs", type=int, default=8, help="envs of the timed rollout")
    parser.add_argument("--train-envs", type=int, default=4, help="envs of the timed training")
    parser.add_argument("--minibatches", type=int, default=24, help="learner minibatches")
    parser.add_argument("--inflow", type=float, default=3600.0)
    parser.add_argument("--demand-s", type=float, default=480.0)
    parser.add_argument("--warmup-s", type=float, default=120.0)
    parser.add_argument("--episode-steps", type=int, default=600)
    parser.add_argument("--rollout-steps", type=int, default=100, help="timed rollout steps")
    parser.add_argument("--updates", type=int, default=1, help="timed training updates (0: none)")
    parser.add_argument(
        "--max-on-road", type=int, default=320, help="windowed max_vehicles (200 overflow)"
    )
    parser.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    parser.add_argument("--train-modes", nargs="+", choices=MODES, default=["windowed"])
    parser.add_argument("--child", choices=MODES, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(measure(args, args.child)))
        return
    print(
        f"{args.inflow:.0f} veh/h for {args.demand_s:.0f} s, {args.episode_steps}-step episodes, "
        f"{os.cpu_count()} CPU cores; env-steps/s of a {args.rollout_steps}-step rollout of "
        f"{args.envs} envs and of {args.updates} training update(s) of {args.train_envs} envs"
    )
    print(
        f"{'mode':<9} {'rollout':>15} {'train':>15} {'on road':>8}  load before -> after\n"
        f"{'':<9} {'wall / CPU s':>15} {'wall / CPU s':>15}"
    )
    results = {}
    for mode in args.modes:
        cmd = [sys.executable, __file__, *sys.argv[1:], "--child", mode]
        done = subprocess.run(cmd, capture_output=True, text=True)
        if done.returncode:
            sys.exit(f"{mode} failed:\n{done.stderr}")
        r = results[mode] = json.loads(done.stdout.strip().splitlines()[-1])
        cells = [f"{r[k][0]:7.1f} /{r[k][1]:6.1f}" if k in r else f"{'-':>15}" for k in KINDS]
        load = " ".join(f"{x:.2f}" for x in r["load_before"])
        load_after = " ".join(f"{x:.2f}" for x in r["load_after"])
        print(
            f"{mode:<9} {cells[0]} {cells[1]} {r['max_on_road']:8d}  {load} -> {load_after}",
            flush=True,
        )
    if len(results) == 2:
        full, win = results["full"], results["windowed"]
        speedups = [
            f"{kind} x{win[kind][0] / full[kind][0]:.1f}"
            f" (CPU time x{win[kind][1] / full[kind][1]:.1f})"
            for kind in KINDS
            if kind in full and kind in win
        ]
        print("windowed over full: " + ", ".join(speedups))


if __name__ == "__main__":
    main()
