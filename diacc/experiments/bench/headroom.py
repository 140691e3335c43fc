"""``diacc bench --headroom``: how much better than human traffic can CAVs do here at all?

A learner can only find gains the scenario and PSAR leave. This benchmark
puts the references side by side for each map: free-flow travel at the
speed limits, pure HDV, ``same-mix`` (the CAV slots driven by human
drivers), the scripted ``heuristic`` under PSAR, the ``cooperative``
baseline, and the heuristic with **100 % CAVs**. If 100 % CAVs cannot beat
pure HDV, there is nothing to learn and the scenario or PSAR must change
first (issue 26).

Two scenario kinds (:mod:`diacc.sim.scenario`):

* ``release`` (default): the paper's one-shot release, N = 25, rho = 0.4,
  D1, on ``train-25`` and ``train-50``.
* ``demand``: vehicles enter at ``inflow_vph`` for ``demand_s`` seconds
  (rho = 0.4, D1, ``train-50``, preset ``zipper`` so that every driver can
  merge); metrics ignore the first ``warmup_s``. Here throughput past the
  reduction is the quantity that cooperation could raise, so the table
  compares throughput as well as delay with pure HDV. The heuristic rows
  give **every** CAV a slot (``cav_slots`` = the episode's CAVs, see
  :meth:`~diacc.sim.scenario.Demand.with_a_slot_per_cav`): with the default 16 slots most CAVs of a
  100 % CAV stream would drive themselves (IDM-MOBIL / SUMO's models) and
  the row would measure humans, not the heuristic. The column ``unslotted
  CAV-steps`` counts steps at which a CAV on the road lacked a slot; it is
  0 for those rows, checked.

Metrics are the evaluator's (:mod:`diacc.envs.metrics`): mean speed, delay per
vehicle against free-flow travel, throughput past the bottleneck, arrived
share, p(WE) and the share of episodes with a collision; means over seeded
episodes (seeds of ``diacc eval --stream legacy``, as its committed results).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from diacc.config import (
    STYLE_PRESETS,
    ConfigError,
    EnvConfig,
    PSARConfig,
    SimConfig,
    resolve_road,
)
from diacc.envs.episode import EpisodeDriver
from diacc.experiments.evaluate import run_episode
from diacc.experiments.grid import Cell
from diacc.experiments.policies import EvalSettings, PolicySpec, build_policy, parse_policy
from diacc.sim.scenario import Scenario
from diacc.sim.state import TrafficState

#: Reference rows: (label, policy name, CAV share; None = the cell's rho).
REFERENCES = (
    ("pure HDV", "pure-hdv", None),
    ("same-mix", "same-mix", None),
    ("heuristic", "heuristic", None),
    ("cooperative", "cooperative", None),
    ("100 % CAVs heuristic", "heuristic", 1.0),
)
#: Names of the reference rows for ``--references`` (same order as REFERENCES).
REFERENCE_NAMES = ("pure-hdv", "same-mix", "heuristic", "cooperative", "cavs-100")
#: Baselines whose CAVs take commands (the others' CAVs do not exist or drive themselves);
#: a checkpoint's CAVs take them too.
COMMANDING = ("heuristic",)
#: Metrics of a row, in print order: (episodes.csv column, header, format).
METRICS = (
    ("mean_speed_mps", "speed m/s", "{:.2f}"),
    ("delay_per_vehicle_s", "delay s/veh", "{:.1f}"),
    ("throughput_vph", "throughput veh/h", "{:.0f}"),
    ("arrived_fraction", "arrived", "{:.0%}"),
    ("p_we", "p(WE)", "{:.1%}"),
    ("p_sce", "p(SCE)", "{:.1%}"),
    ("collision", "collision eps", "{:.0%}"),
)
#: Demand defaults: the committed demand results' (benchmarks/studies/demand-human-traffic).
DEMAND_S = 480.0
WARMUP_S = 120.0
#: Cell of every row (the paper's training cell): N (release), rho, style mix.
RELEASE_N, RHO, MIX = 25, 0.4, "D1"


@dataclass
class HeadroomRow:
    """Means over episodes of one reference on one (backend, map)."""

    backend: str
    map: str
    label: str
    episodes: int
    values: dict[str, float]  # METRICS column (+ unslotted_cav_steps) -> mean over episodes


def pick_references(names: str | None) -> tuple[tuple[str, str, float | None], ...]:
    """The reference rows a comma-separated list of :data:`REFERENCE_NAMES` picks (None: all)."""
    if names is None:
        return REFERENCES
    picked = [n.strip() for n in names.split(",") if n.strip()]
    unknown = [n for n in picked if n not in REFERENCE_NAMES]
    if unknown or not picked:
        raise ConfigError(
            f"unknown --references entry {(unknown or [''])[0]!r}; use some of "
            f"{', '.join(REFERENCE_NAMES)}"
        )
    return tuple(r for n, r in zip(REFERENCE_NAMES, REFERENCES, strict=True) if n in picked)


def free_flow_travel_s(map_name: str, style_preset: str) -> float:
    """Time (s) to drive the whole route at each segment's speed limit (the road the rows'
    env configs resolve: its map with the preset's limits)."""
    road = resolve_road(EnvConfig(map=map_name, sim=SimConfig(style_preset=style_preset)))
    return float(sum(s.length_m / s.speed_limit_mps for s in road.segments))


def demand_scenario(
    inflow_vph: float, demand_s: float = DEMAND_S, warmup_s: float = WARMUP_S
) -> Scenario:
    """The demand scenario of the head-room table (the Scenario checks the numbers)."""
    return Scenario(
        kind="demand",
        inflow_vph=inflow_vph,
        demand_s=demand_s,
        warmup_s=warmup_s,
        cav_penetration=RHO,
        style_mix=MIX,
        cav_slots=16,  # the references that command no CAV keep the table's 16 (make_driver)
    )


class SlotCountingDriver(EpisodeDriver):
    """An :class:`EpisodeDriver` that counts CAV-steps without an agent slot.

    In a demand episode a CAV that finds every slot taken drives itself
    (:mod:`diacc.envs.env`), which would make a heuristic row partly a human one;
    this count shows that it never happened.
    """

    unslotted_cav_steps = 0

    def reset(self, seed: int) -> TrafficState:
        state = super().reset(seed)
        self.unslotted_cav_steps = int(self.env.unserved_cavs)
        return state

    def step(self) -> TrafficState:
        state = super().step()
        self.unslotted_cav_steps += int(self.env.unserved_cavs)
        return state


def make_driver(
    backend: str,
    cell: Cell,
    policy_name: str,
    style_preset: str,
    steps: int,
    horizon: str | None = None,
    demand: Scenario | None = None,
    sampled: bool = False,
) -> SlotCountingDriver:
    """The episode driver of one reference on one cell (the caller closes it).

    ``policy_name``: a baseline or a checkpoint path (``sampled``: its actions drawn
    from its distribution, else the argmax). ``demand``: the demand timing
    (``demand_s``, ``warmup_s``); the cell carries the inflow. Policies in
    :data:`COMMANDING` and checkpoints then get a slot for every CAV.
    """
    spec = PolicySpec(policy_name, sampled=sampled)
    policy = build_policy(spec)
    if demand is not None:
        slots = demand.cav_slots
        if policy_name in COMMANDING or not spec.is_baseline:
            slots = cell.scenario(base=demand).with_a_slot_per_cav().cav_slots
        base = dataclasses.replace(demand, cav_slots=slots)
        sim = dataclasses.replace(policy.base.sim, episode_steps=steps)  # EnvConfig checks warm-up
        policy.base = dataclasses.replace(policy.base, scenario=base, sim=sim)
    # Every row under the same PSAR: a checkpoint trained under an older full_brake rule too.
    full_brake = PSARConfig().full_brake
    settings = EvalSettings(backend, steps, style_preset, horizon, psar_full_brake=full_brake)
    return SlotCountingDriver(policy, policy.env_config(cell, settings))


def measure(
    backend: str,
    cell: Cell,
    policy_name: str,
    episodes: int,
    style_preset: str,
    steps: int,
    horizon: str | None = None,
    demand: Scenario | None = None,
    sampled: bool = False,
) -> dict[str, float]:
    """Mean :data:`METRICS` of ``episodes`` seeded episodes of one policy on one cell,
    and ``unslotted_cav_steps`` (mean per episode); arguments as :func:`make_driver`."""
    driver = make_driver(backend, cell, policy_name, style_preset, steps, horizon, demand, sampled)
    rows, unslotted = [], []
    try:
        for k in range(episodes):
            rows.append(run_episode(driver, cell, k, "legacy").row)
            unslotted.append(driver.unslotted_cav_steps)
    finally:
        driver.close()
    values = {key: float(np.mean([r[key] for r in rows])) for key, _, _ in METRICS}
    values["unslotted_cav_steps"] = float(np.mean(unslotted))
    return values


def _change(value: float, base: float) -> str:
    return f"{(value - base) / base:+.0%}" if base else "n/a"


def run(
    backends: tuple[str, ...] = ("highway",),
    maps: tuple[str, ...] | None = None,
    episodes: int = 4,
    style_preset: str | None = None,
    steps: int | None = None,
    horizon: str | None = None,
    references: tuple[tuple[str, str, float | None], ...] = REFERENCES,
    demand: Scenario | None = None,
    agents: tuple[str, ...] = (),
    agent_actions: tuple[str, ...] = ("greedy",),
) -> list[HeadroomRow]:
    """Measure every reference and print one Markdown table per (backend, map).

    ``agents``: checkpoints (or run directories) measured after the references on
    the same seeded traffic, one row per agent and entry of ``agent_actions``
    (``greedy``, ``sampled``), labelled ``<name> <actions>``: trained agents next
    to what rules and humans reach, under the same PSAR (today's ``full_brake``).

    ``demand``: a ``demand`` :class:`Scenario` (:func:`demand_scenario`) instead of
    the one-shot release; then ``maps`` defaults to ``train-50``, ``style_preset``
    to ``zipper`` and ``steps`` to the demand duration.
    """
    if demand is not None and demand.kind != "demand":
        raise ConfigError(f"head-room demand scenario must be of kind demand, got {demand.kind!r}")
    if maps is None:
        maps = ("train-50",) if demand else ("train-25", "train-50")
    style_preset = style_preset or ("zipper" if demand else "realistic")
    if steps is None:
        steps = int(round(demand.demand_s)) if demand else 330
    if style_preset not in STYLE_PRESETS:
        raise ConfigError(
            f"unknown style preset {style_preset!r}; known: {', '.join(STYLE_PRESETS)}"
        )
    if episodes < 1 or steps < 1:
        raise ConfigError(f"head-room needs episodes >= 1 and steps >= 1, got {episodes}, {steps}")
    unknown = [a for a in agent_actions if a not in ("greedy", "sampled")]
    if unknown:
        raise ConfigError(f"unknown agent actions {unknown[0]!r}; use greedy or sampled")
    rows = [(label, name, rho, False) for label, name, rho in references]
    for agent in agents:  # checked before any episode runs
        path = Path(parse_policy(str(agent)).name)  # a run directory's checkpoint.pt
        name = path.stem if path.parent.name in ("", "checkpoints") else path.parent.name
        rows += [(f"{name} {a}", str(path), None, a == "sampled") for a in agent_actions]
    psar_label = horizon or PSARConfig().horizon  # the horizon the table was made with
    if demand is None:
        what = f"one-shot release N = {RELEASE_N}, rho = {RHO}, {MIX}"
    else:
        what = (
            f"demand {demand.inflow_vph:.0f} veh/h for {demand.demand_s:g} s "
            f"(N = {demand.n_vehicles}), warm-up {demand.warmup_s:g} s, rho = {RHO}, {MIX}"
        )
    print(
        f"head-room: {what}, preset {style_preset}, {episodes} seeded episodes x {steps} "
        f"steps, PSAR horizon {psar_label}, full_brake {PSARConfig().full_brake}"
    )
    headers = [h for _, h, _ in METRICS] + ["unslotted CAV-steps"] * (demand is not None)
    headers += ["delay vs pure HDV", "throughput vs pure HDV"]
    headers += ["delay vs same-mix", "throughput vs same-mix"]
    out, start = [], time.perf_counter()
    for backend in backends:
        for map_name in maps:
            print(
                f"\n{backend}, {map_name}: free-flow travel "
                f"{free_flow_travel_s(map_name, style_preset):.1f} s (delay 0 by definition)"
            )
            print("| reference | " + " | ".join(headers) + " |")
            print("|---" * (len(headers) + 1) + "|")
            base = same_mix = None
            for label, name, rho, sampled in rows:
                if demand is None:
                    cell = Cell(map_name, RELEASE_N, RHO if rho is None else rho, MIX)
                else:
                    share = RHO if rho is None else rho
                    cell = Cell(
                        map_name, demand.n_vehicles, share, MIX, demand.inflow_vph,
                        demand.demand_s, demand.warmup_s,
                    )  # fmt: skip
                values = measure(
                    backend, cell, name, episodes, style_preset, steps, horizon, demand, sampled
                )
                out.append(HeadroomRow(backend, map_name, label, episodes, values))
                base = values if name == "pure-hdv" and rho is None else base
                same_mix = values if name == "same-mix" and rho is None else same_mix
                cells = [fmt.format(values[key]) for key, _, fmt in METRICS]
                if demand is not None:
                    self_driving = name == "cooperative"  # its CAVs never take commands
                    cells.append("n/a" if self_driving else f"{values['unslotted_cav_steps']:.0f}")
                for ref in (base, same_mix):
                    for key in ("delay_per_vehicle_s", "throughput_vph"):
                        cells.append(_change(values[key], ref[key]) if ref else "n/a")
                print(f"| {label} | " + " | ".join(cells) + " |", flush=True)
    print(f"({time.perf_counter() - start:.0f} s)")
    return out
