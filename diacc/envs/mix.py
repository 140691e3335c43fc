"""The cells of a training run's envs: what each block of envs trains on, drawn from the
training mix (:class:`~diacc.config.mix.MixConfig`) or, without one, ``env.map`` and
``extra_maps`` (:func:`~diacc.envs.vector.maps_of_envs`).

A :class:`Cell` is one road, one scenario, one driver preset and one simulator: what
one :class:`~diacc.envs.batch.EnvBatch` holds. The draw of block ``b`` at redraw ``r``
(updates ``r * redraw_every ...``) depends on (run seed, r, b) alone
(:func:`draw_cells`), so a resumed run draws the cells an uninterrupted one drew,
whatever happened before.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from diacc.config import EnvConfig
from diacc.config.mix import MixConfig, cell_scenario
from diacc.sim.maps import map_tag
from diacc.sim.scenario import Scenario

#: First entropy word of the mix's draws (no other seeded stream uses it).
_MIX_TAG = 0x6D1C


@dataclass(frozen=True)
class Cell:
    """What one batch of envs trains on: a map, a scenario, a driver preset, a backend."""

    map: str
    scenario: Scenario
    style_preset: str
    backend: str

    @classmethod
    def of(cls, config: EnvConfig, road_map: str | None = None) -> Cell:
        """``config``'s own cell (on ``road_map`` if given)."""
        return cls(road_map or config.map, config.scenario, config.sim.style_preset, config.backend)

    def env_config(self, config: EnvConfig) -> EnvConfig:
        """``config`` with this cell's map, scenario, preset and backend."""
        sim = config.sim
        if sim.style_preset != self.style_preset:
            sim = dataclasses.replace(sim, style_preset=self.style_preset)
        return dataclasses.replace(
            config, map=self.map, scenario=self.scenario, sim=sim, backend=self.backend
        )

    @property
    def label(self) -> str:
        """One short line: ``train-50 release N23 cav0.41 D2 realistic highway`` (a map
        file by its :func:`~diacc.sim.maps.map_tag`)."""
        s = self.scenario
        size = f"N{s.n_vehicles}" if s.kind == "release" else f"{s.inflow_vph:.0f}vph"
        mix = s.style_mix if isinstance(s.style_mix, str) else "custom"
        share = f"cav{s.cav_penetration:.2f}"
        tail = f"{self.style_preset} {self.backend}"
        return f"{map_tag(self.map)} {s.kind} {size} {share} {mix} {tail}"


def redraw_index(mix: MixConfig, update: int) -> int:
    """The redraw whose cells update ``update`` (0-based) trains on."""
    return update // mix.redraw_every


def draw_cells(mix: MixConfig, base: Scenario, run_seed: int, redraw: int) -> list[Cell]:
    """Each block's cell at redraw ``redraw``: map, kind, style mix and preset uniformly
    among those listed, N (a release, an integer), the CAV share and the inflow (a
    demand) uniformly in their ranges, the backend in turn (block ``b``:
    ``backends[b % len]``, no draw); ``base`` (``env.scenario``) gives the rest."""
    maps = mix.map_names()
    cells = []
    for block in range(mix.blocks):
        rng = np.random.default_rng(np.random.SeedSequence([_MIX_TAG, run_seed, redraw, block]))
        road_map = maps[rng.integers(len(maps))]
        kind = mix.kind[rng.integers(len(mix.kind))]
        style_mix = mix.style_mix[rng.integers(len(mix.style_mix))]
        preset = mix.style_preset[rng.integers(len(mix.style_preset))]
        n_vehicles = int(rng.integers(mix.n_vehicles[0], mix.n_vehicles[1] + 1))
        share = float(rng.uniform(mix.cav_penetration[0], mix.cav_penetration[1]))
        inflow = float(rng.uniform(mix.inflow_vph[0], mix.inflow_vph[1]))
        scenario = cell_scenario(base, kind, share, style_mix, n_vehicles, inflow, mix.demand_s)
        backend = mix.backends[block % len(mix.backends)]
        cells.append(Cell(road_map, scenario, preset, backend))
    return cells


def cells_of_envs(block_cells: list[Cell], n_envs: int) -> list[Cell]:
    """The cell of each of ``n_envs`` envs: one near-equal contiguous block per entry."""
    shares = np.array_split(np.arange(n_envs), len(block_cells))
    return [cell for cell, share in zip(block_cells, shares, strict=True) for _ in share]


def describe(block_cells: list[Cell], n_envs: int) -> str:
    """The log's line of a draw: each block's envs and cell."""
    shares = np.array_split(np.arange(n_envs), len(block_cells))
    return "; ".join(
        f"envs {share[0]}-{share[-1]}: {cell.label}"
        for cell, share in zip(block_cells, shares, strict=True)
    )
