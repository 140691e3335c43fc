"""Human traffic of the ``demand`` scenario kind: outflow, capacity drop, lane-end waits.

Runs the backends directly (no agents: every vehicle an HDV), one seeded
episode per (traffic, backend, inflow, seed), and prints one JSON line each.
Traffic ``pure-hdv``: every vehicle drawn as an HDV of the mix; ``same-mix``:
the draw of a 40 % CAV cell with its CAV slots driven by normal human drivers
(:attr:`diacc.sim.scenario.Scenario.cav_slot_style`). What it measures, after
``--warmup-s``:

* ``outflow_vph``: vehicles crossing the end of the reduction segment, per hour.
* ``pre_breakdown_vph`` / ``discharge_vph``: the highest 30 s outflow before the
  breakdown (the first 30 s bin, from t = 0, whose mean speed 100 m upstream of
  the lane drop falls below ``--breakdown-mps``) and the mean outflow after the
  warm-up and one bin past the breakdown. A capacity drop is
  ``discharge_vph < pre_breakdown_vph``.
* ``max_lane_end_wait_s``: longest a vehicle stood (< 0.5 m/s) within 50 m of
  the end of its lane.
* speed, p(WE), throughput past the reduction, delay per vehicle, arrived share:
  :class:`diacc.envs.metrics.EpisodeRecorder` (its ``throughput_vph`` is ``outflow_vph``
  counted by the recorder).

The committed results/demand/humans.jsonl (benchmarks/README.md):
    python benchmarks/demand_bottleneck.py --traffic pure-hdv same-mix --inflow 2000 4400 \
        --seeds 2 --demand-s 480 --warmup-s 120 --preset zipper \
        --out benchmarks/results/demand/humans.jsonl
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from diacc.config import EventConfig, SimConfig, preset_road
from diacc.envs.metrics import EpisodeRecorder
from diacc.experiments.bench import write_json_lines
from diacc.sim.backends.base import CavCommands, make_backend
from diacc.sim.maps import load_map
from diacc.sim.scenario import Scenario

BIN_S = 30.0
STANDING_MPS = 0.5
LANE_END_ZONE_M = 50.0


def run(traffic: str, backend: str, map_name: str, inflow_vph: float, seed: int, args) -> dict:
    humans = {
        "pure-hdv": {"cav_penetration": 0.0},
        "same-mix": {"cav_penetration": 0.4, "cav_slot_style": "normal"},
    }[traffic]
    scenario = Scenario(
        kind="demand", inflow_vph=inflow_vph, demand_s=args.demand_s, warmup_s=args.warmup_s,
        style_mix=args.mix, **humans,
    )  # fmt: skip
    sim = SimConfig(episode_steps=int(args.demand_s), style_preset=args.preset)
    road = preset_road(load_map(map_name), sim.style_preset)
    sim_backend = make_backend(backend, road, sim)
    recorder = EpisodeRecorder(road, EventConfig(), scenario.warmup_s)
    reduction = next(i for i, s in enumerate(road.segments) if s.kind.startswith("reduction"))
    red_end_m = road.segment_ends_m[reduction]
    drop_m = road.segment_starts_m[reduction]
    lane_end = road.lane_end_m()  # (S, L)
    t0 = time.perf_counter()
    state = sim_backend.reset(scenario, seed)
    recorder.record(state)
    n = state.n_vehicles
    passed = np.zeros(n, bool)  # (V,) crossed the reduction end
    cross_t = []  # crossing times
    standing_s = np.zeros(n)  # (V,) current standing spell at a lane end
    longest_s = np.zeros(n)
    upstream = []  # (t, mean speed 100 m before the drop)
    for _ in range(sim.episode_steps):
        state = sim_backend.step(CavCommands.idle(n))
        recorder.record(state)
        now = state.x_m >= red_end_m
        new = (now | state.arrived) & ~passed
        cross_t += [state.time_s] * int(new.sum())
        passed |= new
        end = lane_end[state.segment, state.lane]  # (V,)
        at_end = (
            state.active & (end - state.x_m < LANE_END_ZONE_M) & (state.speed_mps < STANDING_MPS)
        )
        standing_s = np.where(at_end, standing_s + sim.step_s, 0.0)
        longest_s = np.maximum(longest_s, standing_s)
        near = state.active & (state.x_m > drop_m - 100.0) & (state.x_m < drop_m)
        upstream.append((state.time_s, state.speed_mps[near].mean() if near.any() else np.nan))
    sim_backend.close()
    m = recorder.summary()
    cross_t = np.array(cross_t)
    t_end = sim.episode_steps * sim.step_s
    edges = np.arange(0.0, t_end + 1e-9, BIN_S)
    counts = np.histogram(cross_t, edges)[0]
    bin_vph = counts * 3600.0 / BIN_S  # (B,)
    up = np.array(upstream)
    bin_speed = np.array(
        [np.nanmean(up[(up[:, 0] > a) & (up[:, 0] <= a + BIN_S), 1]) for a in edges[:-1]]
    )
    broken = np.flatnonzero(bin_speed < args.breakdown_mps)
    if broken.size and broken[0] > 0:
        pre = float(bin_vph[: broken[0]].max())
        after = max(broken[0] + 1, int(np.ceil(args.warmup_s / BIN_S)))
        discharge = float(bin_vph[after:].mean()) if after < len(bin_vph) else None
    else:
        pre, discharge = None, None
    return {
        "traffic": traffic,
        "preset": args.preset,
        "backend": backend,
        "map": map_name,
        "inflow_vph": inflow_vph,
        "seed": seed,
        "vehicles": n,
        "outflow_vph": float(((cross_t >= args.warmup_s).sum()) * 3600.0 / (t_end - args.warmup_s)),
        "pre_breakdown_vph": pre,
        "discharge_vph": discharge,
        "breakdown_bin": int(broken[0]) if broken.size else None,
        "bin_vph": bin_vph.tolist(),
        "max_lane_end_wait_s": float(longest_s.max()),
        "mean_speed_mps": m.mean_speed_mps,
        "p_we": m.p_we,
        "throughput_vph": m.throughput_vph,
        "delay_per_vehicle_s": m.delay_per_vehicle_s,
        "arrived_fraction": m.arrived_fraction,
        "mean_travel_time_s": m.mean_travel_time_s,
        "n_collisions": m.n_collisions,
        "seconds": round(time.perf_counter() - t0, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--traffic", nargs="+", default=["pure-hdv"], choices=["pure-hdv", "same-mix"]
    )
    parser.add_argument("--backend", nargs="+", default=["highway", "sumo"])
    parser.add_argument("--map", default="train-50")
    parser.add_argument("--inflow", nargs="+", type=float, default=[1600, 2400, 3200, 3600])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--demand-s", type=float, default=600.0)
    parser.add_argument("--warmup-s", type=float, default=180.0)
    parser.add_argument("--breakdown-mps", type=float, default=10.0)
    parser.add_argument("--mix", default="D1")
    parser.add_argument("--preset", default="realistic")
    parser.add_argument("--out", default=None, help="append JSON lines here")
    args = parser.parse_args()
    records = (
        run(traffic, backend, args.map, inflow, seed, args)
        for inflow in args.inflow
        for traffic in args.traffic
        for backend in args.backend
        for seed in range(args.seeds)
    )
    write_json_lines(records, args.out)


if __name__ == "__main__":
    main()
