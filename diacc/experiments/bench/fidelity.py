"""``diacc bench --fidelity``: do the two simulators agree on the bottleneck's capacity?

A result prototyped on the highway backend says something about SUMO only if
both pass the same human traffic. This benchmark feeds pure human traffic
into the ``demand`` scenario (``train-50``, vehicles entering at each inflow
for ``demand_s``, metrics after ``warmup_s``) on both backends, one seeded
episode per (backend, inflow, seed) with the same arrival sequence, and
prints per inflow the outflow past the reduction of each backend side by
side, their ratio, the delay per vehicle and in how many runs a capacity
drop was seen (issue 44's target: highway within 10 % of SUMO at every
inflow, the drop present on both).

:func:`human_flow` measures one episode, also for
``benchmarks/studies/demand-human-traffic/run.py`` (which writes the JSON lines of
``benchmarks/studies/demand-human-traffic/results/``):

* ``outflow_vph``: vehicles crossing the end of the reduction segment after
  the warm-up, per hour.
* ``pre_breakdown_vph`` / ``discharge_vph``: the highest 30 s outflow before
  the breakdown (the first 30 s bin, from t = 0, whose mean speed 100 m
  upstream of the lane drop falls below ``breakdown_mps``) and the mean
  outflow after the warm-up and one bin past the breakdown. A capacity drop
  is ``discharge_vph < pre_breakdown_vph``.
* ``max_lane_end_wait_s``: longest a vehicle stood (< 0.5 m/s) within 50 m
  of the end of its lane.
* speed, p(WE), throughput past the reduction, delay per vehicle, arrived
  share: :class:`diacc.envs.metrics.EpisodeRecorder`.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass

import numpy as np

from diacc.config import BACKENDS, EnvConfig, SimConfig, resolve_road
from diacc.envs.metrics import EpisodeRecorder
from diacc.sim.backends.base import CavCommands, make_backend
from diacc.sim.scenario import Scenario

BIN_S = 30.0
STANDING_MPS = 0.5
LANE_END_ZONE_M = 50.0
#: Inflows (veh/h) of the default table: from below the drop's capacity to oversaturation.
INFLOWS_VPH = (2400.0, 3200.0, 4000.0, 4800.0)
#: Largest relative outflow difference, highway against SUMO, that counts as agreement.
TARGET_OUTFLOW_DIFF = 0.10
#: Human traffic of :func:`human_flow`: scenario overrides of each kind.
TRAFFIC = {
    "pure-hdv": {"cav_penetration": 0.0},
    "same-mix": {"cav_penetration": 0.4, "cav_slot_style": "normal"},
}


@dataclass(frozen=True)
class FlowSettings:
    """The demand episode :func:`human_flow` plays (defaults: the committed results')."""

    map_name: str = "train-50"
    demand_s: float = 480.0
    warmup_s: float = 120.0
    breakdown_mps: float = 10.0
    mix: str = "D1"
    preset: str = "realistic"
    highway_merges: str = "late"  # SimConfig.highway_merges (the highway backend's merges)


def human_flow(
    traffic: str, backend: str, inflow_vph: float, seed: int, settings: FlowSettings
) -> dict:
    """One seeded demand episode of human traffic (module docstring); a JSON-able record."""
    scenario = Scenario(
        kind="demand",
        inflow_vph=inflow_vph,
        demand_s=settings.demand_s,
        warmup_s=settings.warmup_s,
        style_mix=settings.mix,
        **TRAFFIC[traffic],
    )
    sim = SimConfig(
        episode_steps=int(settings.demand_s),
        style_preset=settings.preset,
        highway_merges=settings.highway_merges,
    )
    config = EnvConfig(backend=backend, map=settings.map_name, scenario=scenario, sim=sim)
    road = resolve_road(config)
    sim_backend = make_backend(backend, road, sim)
    recorder = EpisodeRecorder(road, config.events, scenario.warmup_s)
    reduction = next(i for i, s in enumerate(road.segments) if s.kind.startswith("reduction"))
    red_end_m = road.segment_ends_m[reduction]
    drop_m = road.segment_starts_m[reduction]
    lane_end = road.lane_end_m()  # (S, L)
    t0 = time.perf_counter()
    try:
        batch = sim_backend.reset(scenario, seed)  # a batch of one
        recorder.record(batch)
        n = batch.n_vehicles
        passed = np.zeros(n, bool)  # (V,) crossed the reduction end
        cross_t = []  # crossing times
        standing_s = np.zeros(n)  # (V,) current standing spell at a lane end
        longest_s = np.zeros(n)
        upstream = []  # (t, mean speed 100 m before the drop)
        for _ in range(sim.episode_steps):
            batch = sim_backend.step(CavCommands.idle(n))
            recorder.record(batch)
            now = batch.x_m[0] >= red_end_m
            new = (now | batch.arrived[0]) & ~passed
            cross_t += [float(batch.time_s[0])] * int(new.sum())
            passed |= new
            end = lane_end[batch.segment[0], batch.lane[0]]  # (V,)
            at_end = (
                batch.active[0]
                & (end - batch.x_m[0] < LANE_END_ZONE_M)
                & (batch.speed_mps[0] < STANDING_MPS)
            )
            standing_s = np.where(at_end, standing_s + sim.step_s, 0.0)
            longest_s = np.maximum(longest_s, standing_s)
            near = batch.active[0] & (batch.x_m[0] > drop_m - 100.0) & (batch.x_m[0] < drop_m)
            upstream.append(
                (float(batch.time_s[0]), batch.speed_mps[0][near].mean() if near.any() else np.nan)
            )
    finally:
        sim_backend.close()
    m = recorder.summary()
    cross_t = np.array(cross_t)
    t_end = sim.episode_steps * sim.step_s
    edges = np.arange(0.0, t_end + 1e-9, BIN_S)
    counts = np.histogram(cross_t, edges)[0]
    bin_vph = counts * 3600.0 / BIN_S  # (B,)
    up = np.array(upstream)
    with warnings.catch_warnings():  # a bin without a vehicle near the drop is NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        bin_speed = np.array(
            [np.nanmean(up[(up[:, 0] > a) & (up[:, 0] <= a + BIN_S), 1]) for a in edges[:-1]]
        )
    broken = np.flatnonzero(bin_speed < settings.breakdown_mps)
    if broken.size and broken[0] > 0:
        pre = float(bin_vph[: broken[0]].max())
        after = max(broken[0] + 1, int(np.ceil(settings.warmup_s / BIN_S)))
        discharge = float(bin_vph[after:].mean()) if after < len(bin_vph) else None
    else:
        pre, discharge = None, None
    return {
        "traffic": traffic,
        "preset": settings.preset,
        "highway_merges": settings.highway_merges,
        "backend": backend,
        "map": settings.map_name,
        "inflow_vph": inflow_vph,
        "seed": seed,
        "vehicles": n,
        "outflow_vph": float(
            ((cross_t >= settings.warmup_s).sum()) * 3600.0 / (t_end - settings.warmup_s)
        ),
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


def capacity_drop(record: dict) -> bool:
    """Did this run's outflow fall after the breakdown (discharge below the best before)?"""
    pre, discharge = record["pre_breakdown_vph"], record["discharge_vph"]
    return pre is not None and discharge is not None and discharge < pre


def run(
    inflows_vph: tuple[float, ...] = INFLOWS_VPH,
    seeds: int = 1,
    settings: FlowSettings = FlowSettings(),
    backends: tuple[str, ...] = BACKENDS,
) -> list[dict]:
    """Measure every (inflow, backend, seed) and print one Markdown table; returns the records."""
    print(
        f"simulator fidelity: pure HDV on {settings.map_name}, demand {settings.demand_s:g} s "
        f"(metrics after {settings.warmup_s:g} s), style preset {settings.preset}, mix "
        f"{settings.mix}, highway merges {settings.highway_merges}, {seeds} seed(s) per inflow; "
        "outflow past the reduction, veh/h"
    )
    columns = " | ".join(f"{b} outflow | {b} delay s/veh | {b} capacity drop" for b in backends)
    print(f"| inflow veh/h | {columns} | highway vs sumo |")
    print("|---" * (2 + 3 * len(backends)) + "|")
    records, start = [], time.perf_counter()
    for inflow in inflows_vph:
        by_backend = {}
        for backend in backends:
            rows = [human_flow("pure-hdv", backend, inflow, s, settings) for s in range(seeds)]
            records += rows
            by_backend[backend] = rows
        cells = []
        for backend in backends:
            rows = by_backend[backend]
            cells += [
                f"{np.mean([r['outflow_vph'] for r in rows]):.0f}",
                f"{np.mean([r['delay_per_vehicle_s'] for r in rows]):.1f}",
                f"{sum(capacity_drop(r) for r in rows)} of {len(rows)}",
            ]
        ratio = ""
        if {"highway", "sumo"} <= set(by_backend):
            out = {b: np.mean([r["outflow_vph"] for r in by_backend[b]]) for b in by_backend}
            diff = out["highway"] / out["sumo"] - 1.0
            within = "within" if abs(diff) <= TARGET_OUTFLOW_DIFF else "**outside**"
            ratio = f"{diff:+.1%} ({within} {TARGET_OUTFLOW_DIFF:.0%})"
        print(f"| {inflow:.0f} | {' | '.join(cells)} | {ratio} |", flush=True)
    print(f"({time.perf_counter() - start:.0f} s)")
    return records
