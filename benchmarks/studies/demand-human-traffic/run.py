"""Human traffic of the ``demand`` scenario kind: outflow, capacity drop, lane-end waits.

Runs the backends directly (no agents: every vehicle an HDV), one seeded
episode per (traffic, backend, inflow, seed), and prints one JSON line each.
Traffic ``pure-hdv``: every vehicle drawn as an HDV of the mix; ``same-mix``:
the draw of a 40 % CAV cell with its CAV slots driven by normal human drivers
(:attr:`diacc.sim.scenario.Scenario.cav_slot_style`). What each line holds:
:func:`diacc.experiments.bench.fidelity.human_flow` (``diacc bench --fidelity``
prints the same runs of pure HDV as a side-by-side table).

The committed results/humans.jsonl (README.md of this folder):
    python benchmarks/studies/demand-human-traffic/run.py --traffic pure-hdv same-mix \\
        --inflow 2000 4400 --seeds 2 --demand-s 480 --warmup-s 120 --preset zipper \\
        --out benchmarks/studies/demand-human-traffic/results/humans.jsonl
"""

from __future__ import annotations

import argparse

from diacc.experiments.bench import write_json_lines
from diacc.experiments.bench.fidelity import TRAFFIC, FlowSettings, human_flow


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--traffic", nargs="+", default=["pure-hdv"], choices=list(TRAFFIC))
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
    settings = FlowSettings(
        map_name=args.map,
        demand_s=args.demand_s,
        warmup_s=args.warmup_s,
        breakdown_mps=args.breakdown_mps,
        mix=args.mix,
        preset=args.preset,
    )
    records = (
        human_flow(traffic, backend, inflow, seed, settings)
        for inflow in args.inflow
        for traffic in args.traffic
        for backend in args.backend
        for seed in range(args.seeds)
    )
    write_json_lines(records, args.out)


if __name__ == "__main__":
    main()
