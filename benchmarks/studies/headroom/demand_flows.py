"""Why 100 % CAVs do or do not raise throughput on the demand kind: entry flow vs outflow.

``diacc bench --headroom --scenario demand`` reports throughput past the
reduction. That throughput cannot exceed the flow that gets onto the road,
so this script measures both, per (backend, inflow, reference, seed), with
the bench's own drivers (:func:`diacc.experiments.bench.headroom.make_driver`: the
heuristic drives every CAV), after ``--warmup-s``:

* ``entry_vph``: vehicles that entered the route, per hour;
* ``outflow_vph``: vehicles past the end of the reduction, per hour;
* ``mean_entry_lag_s`` / ``max_entry_lag_s``: how late vehicles entered
  against their scheduled departure (a queue at the entry holds them back);
* ``bin_out_vph``: the outflow per 30 s bin from t = 0.

If pure HDV already passes the whole demand, no policy can raise its
throughput at that inflow; if 100 % CAVs pass all they are given, the demand,
not the reduction, is their limit. One JSON line per episode.

    python benchmarks/studies/headroom/demand_flows.py --backend highway sumo --inflow 3600 \\
        --seeds 1 --out benchmarks/studies/headroom/results/demand-entry-vs-outflow.jsonl
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from diacc.experiments.bench import headroom, write_json_lines
from diacc.experiments.grid import Cell
from diacc.sim.scenario import draw_population

BIN_S = 30.0
#: reference label -> (policy, CAV share)
REFERENCES = {"pure-hdv": ("pure-hdv", 0.4), "cav100-heuristic": ("heuristic", 1.0)}


def run(backend: str, inflow_vph: float, reference: str, episode: int, args) -> dict:
    demand = headroom.demand_scenario(inflow_vph, args.demand_s, args.warmup_s)
    policy, share = REFERENCES[reference]
    cell = Cell(args.map, demand.n_vehicles, share, headroom.MIX, inflow_vph)
    steps = int(round(args.demand_s))
    driver = headroom.make_driver(backend, cell, policy, args.preset, steps, args.horizon, demand)
    t0 = time.perf_counter()
    try:
        seed = cell.seed(episode)
        state = driver.reset(seed)
        road = driver.road
        depart_s = draw_population(driver.cfg.scenario, road, seed).depart_s  # (V,)
        reduction = next(i for i, s in enumerate(road.segments) if s.kind.startswith("reduction"))
        red_end_m = road.segment_ends_m[reduction]
        n = state.n_vehicles
        entered_s = np.full(n, np.nan)  # (V,) first time on the road
        passed_s = np.full(n, np.nan)  # (V,) first time past the reduction end
        while True:
            seen = (state.active | state.arrived) & np.isnan(entered_s)
            entered_s[seen] = state.time_s
            past = ((state.x_m >= red_end_m) | state.arrived) & np.isnan(passed_s)
            passed_s[past] = state.time_s
            if driver.done:
                break
            state = driver.step()
        collisions = len(state.collisions)
        unslotted = driver.unslotted_cav_steps
    finally:
        driver.close()
    t_end = steps * driver.cfg.sim.step_s
    window_h = (t_end - args.warmup_s) / 3600.0
    lag_s = (entered_s - depart_s)[np.isfinite(entered_s)]
    edges = np.arange(0.0, t_end + 1e-9, BIN_S)
    return {
        "backend": backend,
        "inflow_vph": inflow_vph,
        "reference": reference,
        "episode": episode,
        "seed": seed,
        "preset": args.preset,
        "horizon": args.horizon,
        "entry_vph": float(np.sum(entered_s >= args.warmup_s) / window_h),
        "outflow_vph": float(np.sum(passed_s >= args.warmup_s) / window_h),
        "mean_entry_lag_s": float(lag_s.mean()),
        "max_entry_lag_s": float(lag_s.max()),
        "not_entered": int(np.sum(np.isnan(entered_s) & (depart_s < t_end))),
        "bin_out_vph": (np.histogram(passed_s[np.isfinite(passed_s)], edges)[0] * 3600 / BIN_S)
        .astype(int)
        .tolist(),
        "collisions": collisions,
        "unslotted_cav_steps": unslotted,
        "seconds": round(time.perf_counter() - t0, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backend", nargs="+", default=["highway", "sumo"])
    parser.add_argument("--inflow", nargs="+", type=float, default=[3600.0])
    parser.add_argument("--reference", nargs="+", default=list(REFERENCES), choices=REFERENCES)
    parser.add_argument("--seeds", type=int, default=1)
    parser.add_argument("--map", default="train-50")
    parser.add_argument("--demand-s", type=float, default=headroom.DEMAND_S)
    parser.add_argument("--warmup-s", type=float, default=headroom.WARMUP_S)
    parser.add_argument("--preset", default="zipper")
    parser.add_argument("--horizon", default="headway")
    parser.add_argument("--out", default=None, help="append JSON lines here")
    args = parser.parse_args()
    records = (
        run(backend, inflow, reference, episode, args)
        for inflow in args.inflow
        for backend in args.backend
        for reference in args.reference
        for episode in range(args.seeds)
    )
    write_json_lines(records, args.out)


if __name__ == "__main__":
    main()
