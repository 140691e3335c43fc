"""``diacc bench --headroom``: how much better than human traffic can CAVs do here at all?

A learner can only find gains the scenario and PSAR leave. This benchmark
puts the references side by side for each training map (one-shot release,
N = 25, D1): free-flow travel at the speed limits, pure HDV, ``same-mix``
(the CAV slots driven by human drivers), the scripted ``heuristic`` under
PSAR, the ``cooperative`` baseline, and the heuristic with **100 % CAVs**.
If 100 % CAVs cannot beat pure HDV on delay, there is nothing to learn and
the scenario or PSAR must change first (issue 26).

Metrics are the evaluator's (:mod:`diacc.metrics`): mean speed, delay per
vehicle against free-flow travel, throughput past the bottleneck, arrived
share, p(WE) and the share of episodes with a collision; means over seeded
episodes (seeds as ``diacc eval``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from diacc.config import STYLE_PRESETS, ConfigError, preset_road
from diacc.episode import EpisodeDriver
from diacc.evaluate import run_episode
from diacc.grid import Cell
from diacc.maps import load_map
from diacc.policies import EvalSettings, PolicySpec, build_policy

#: Reference rows: (label, policy name, CAV share; None = the cell's rho).
REFERENCES = (
    ("pure HDV", "pure-hdv", None),
    ("same-mix", "same-mix", None),
    ("heuristic", "heuristic", None),
    ("cooperative", "cooperative", None),
    ("100 % CAVs heuristic", "heuristic", 1.0),
)
#: Metrics of a row, in print order: (episodes.csv column, header, format).
METRICS = (
    ("mean_speed_mps", "speed m/s", "{:.2f}"),
    ("delay_per_vehicle_s", "delay s/veh", "{:.1f}"),
    ("throughput_vph", "throughput veh/h", "{:.0f}"),
    ("arrived_fraction", "arrived", "{:.0%}"),
    ("p_we", "p(WE)", "{:.1%}"),
    ("collision", "collision eps", "{:.0%}"),
)


@dataclass
class HeadroomRow:
    """Means over episodes of one reference on one (backend, map)."""

    backend: str
    map: str
    label: str
    episodes: int
    values: dict[str, float]  # METRICS column -> mean over episodes


def free_flow_travel_s(map_name: str, style_preset: str) -> float:
    """Time (s) to drive the whole route at each segment's speed limit."""
    road = preset_road(load_map(map_name), style_preset)
    return float(sum(s.length_m / s.speed_limit_mps for s in road.segments))


def measure(
    backend: str,
    cell: Cell,
    policy_name: str,
    episodes: int,
    style_preset: str,
    steps: int,
    horizon: str | None = None,
) -> dict[str, float]:
    """Mean :data:`METRICS` of ``episodes`` seeded episodes of one policy on one cell."""
    policy = build_policy(PolicySpec(policy_name))
    settings = EvalSettings(backend, steps, style_preset, psar_horizon=horizon)
    driver = EpisodeDriver(policy, policy.env_config(cell, settings))
    try:
        rows = [run_episode(driver, cell, k).row for k in range(episodes)]
    finally:
        driver.close()
    return {key: float(np.mean([r[key] for r in rows])) for key, _, _ in METRICS}


def run(
    backends: tuple[str, ...] = ("highway",),
    maps: tuple[str, ...] = ("train-25", "train-50"),
    episodes: int = 4,
    style_preset: str = "realistic",
    steps: int = 330,
    horizon: str | None = None,
    references: tuple[tuple[str, str, float | None], ...] = REFERENCES,
) -> list[HeadroomRow]:
    """Measure every reference and print one Markdown table per (backend, map)."""
    if style_preset not in STYLE_PRESETS:
        raise ConfigError(
            f"unknown style preset {style_preset!r}; known: {', '.join(STYLE_PRESETS)}"
        )
    if episodes < 1 or steps < 1:
        raise ConfigError(f"head-room needs episodes >= 1 and steps >= 1, got {episodes}, {steps}")
    psar_label = horizon or "default"
    print(
        f"head-room: one-shot release N = 25, rho = 0.4, D1, preset {style_preset}, "
        f"{episodes} seeded episodes x {steps} steps, PSAR horizon {psar_label}"
    )
    out, start = [], time.perf_counter()
    for backend in backends:
        for map_name in maps:
            print(
                f"\n{backend}, {map_name}: free-flow travel "
                f"{free_flow_travel_s(map_name, style_preset):.1f} s (delay 0 by definition)"
            )
            print(
                "| reference | " + " | ".join(h for _, h, _ in METRICS) + " | delay vs pure HDV |"
            )
            print("|---" * (len(METRICS) + 2) + "|")
            base_delay = None
            for label, name, rho in references:
                cell = Cell(map_name, 25, 0.4 if rho is None else rho, "D1")
                values = measure(backend, cell, name, episodes, style_preset, steps, horizon)
                out.append(HeadroomRow(backend, map_name, label, episodes, values))
                delay = values["delay_per_vehicle_s"]
                base_delay = delay if base_delay is None else base_delay
                change = (delay - base_delay) / base_delay if base_delay else float("nan")
                cells = [fmt.format(values[key]) for key, _, fmt in METRICS]
                print(f"| {label} | " + " | ".join(cells) + f" | {change:+.0%} |", flush=True)
    print(f"({time.perf_counter() - start:.0f} s)")
    return out
