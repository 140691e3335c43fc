"""The training mix (``[mix]``, :class:`MixConfig`): a distribution of roads and traffic a
run samples its episodes from, instead of the one cell ``env.map`` + ``env.scenario`` +
``env.sim.style_preset`` (docs/concepts/maps.md, "Training on a mix of roads and traffic").

Here the settings and what follows from them without drawing anything: the maps
(:meth:`MixConfig.map_names`), the scenario of any point of the distribution
(:func:`cell_scenario`) and its corners (:func:`corner_scenarios`), which bound the
agent slots every env is padded to (:func:`diacc.config.checks.train_slots`) and the
vehicles a cell can hold (checked by :func:`diacc.config.checks.validate`). The draws themselves are
:mod:`diacc.envs.mix`'s.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from diacc.config.env import EnvConfig
from diacc.fields import MAX_ENVS, MAX_INFLOW_VPH, MAX_VEHICLES, ConfigError, check_fields, ranged
from diacc.sim.drivers import STYLE_PRESETS
from diacc.sim.mapgen import STREAM_SEEDS, generated_names
from diacc.sim.scenario import EVERY_CAV, SCENARIO_KINDS, STYLE_MIXES, Scenario
from diacc.sim.settings import BACKENDS, SimConfig

#: A demand's inflow when none is set (:class:`~diacc.sim.scenario.Demand`'s default).
_DEFAULT_INFLOW_VPH = Scenario(kind="demand").inflow_vph
#: Where the run's own value of a dimension is set, when not in ``env.scenario``.
_RUN_FIELD = {"style_preset": "env.sim.style_preset", "backends": "env.backend"}
#: Range fields: (low, high), both inclusive, drawn uniformly (N as an integer).
RANGES = ("n_vehicles", "cav_penetration", "inflow_vph")
#: Choice fields: each drawn uniformly among the names listed.
CHOICES = {"style_mix": tuple(STYLE_MIXES), "style_preset": tuple(STYLE_PRESETS)}


@dataclass(frozen=True)
class MixConfig:
    """A distribution of training cells (map, traffic, driver preset); off when it names
    no map (the default: the run trains on ``env.map`` and ``extra_maps`` as before).

    The environments are split into ``blocks`` contiguous blocks; every
    ``redraw_every`` updates each block draws its cell anew from the distribution
    (:func:`diacc.envs.mix.draw_cells`). A cell's scenario is ``env.scenario`` with the
    drawn kind, CAV share, style mix and N (a release) or inflow (a demand, which gives
    every CAV of its ``demand_s`` seconds an agent slot); its other settings (insertion,
    warm-up) are ``env.scenario``'s. The agent slots of every env are padded to the most
    any cell can have (:func:`~diacc.config.checks.train_slots`). A dimension the mix
    leaves out (empty) is the run's own: ``env.scenario``'s N, CAV share, style mix and
    kind, ``env.sim.style_preset`` (:meth:`following`, applied when the
    :class:`~diacc.config.train.TrainConfig` is built), so a mix varies what it lists and
    nothing the user set is dropped; a dimension set both here and, to another value
    than its default, in ``env`` is refused; ``configs/suite-train.toml`` lists them all.
    """

    # shipped names, .toml paths or generated names (gen-train-3)
    maps: tuple[str, ...] = ()
    # and the first this many maps of the generated training stream (gen-train-0, ...)
    generated_maps: int = ranged(0, 0, STREAM_SEEDS, why="the training stream's maps")
    # every dimension: () = the run's own (env.scenario's, env.sim.style_preset)
    n_vehicles: tuple[int, ...] = ranged((), 1, MAX_VEHICLES)  # a release's N
    cav_penetration: tuple[float, ...] = ranged((), 0, 1)
    style_mix: tuple[str, ...] = ()
    style_preset: tuple[str, ...] = ()
    kind: tuple[str, ...] = ()
    # each block's simulator, given in turn (block b: backends[b % len]), not drawn: every
    # update then trains on each one listed, and no draw of the other dimensions moves
    backends: tuple[str, ...] = ()
    inflow_vph: tuple[float, ...] = ranged(
        (), 0, MAX_INFLOW_VPH, open_low=True, why="more than 4 lanes carry"
    )  # a demand's
    # a demand's duration: inflow_vph's high end x demand_s makes its most vehicles, which
    # env.obs.max_vehicles bounds (validate)
    demand_s: float = ranged(30.0, 0, open_low=True)
    blocks: int = ranged(4, 1, MAX_ENVS, why="each block is a simulator")  # <= n_envs
    redraw_every: int = ranged(1, 1)  # updates between draws

    def __post_init__(self) -> None:
        check_fields(self)
        if any(isinstance(n, bool) or not isinstance(n, int) for n in self.n_vehicles):
            raise ConfigError(f"mix.n_vehicles must be integers, got {list(self.n_vehicles)}")
        for name in RANGES:
            value = getattr(self, name)
            if value and (len(value) != 2 or value[0] > value[1]):
                raise ConfigError(
                    f"mix.{name} must be a range [low, high] with low <= high, got {list(value)}"
                )
        for name, known in (*CHOICES.items(), ("kind", SCENARIO_KINDS), ("backends", BACKENDS)):
            value = getattr(self, name)
            unknown = [v for v in value if v not in known]
            if unknown:
                raise ConfigError(f"mix.{name}: unknown {unknown[0]!r}; known: {', '.join(known)}")

    @property
    def on(self) -> bool:
        """Whether the run trains on the mix (it names a map)."""
        return bool(self.maps) or self.generated_maps > 0

    def following(self, scenario: Scenario, style_preset: str, backend: str) -> MixConfig:
        """This mix with every dimension it leaves out taken from the run's own cell
        (``env.scenario``, ``env.sim.style_preset``, ``env.backend``); a dimension it sets
        that the run also sets to a value other than the default is refused (one would be
        dropped)."""
        if not self.on:
            return self
        own: dict[str, tuple] = {
            "n_vehicles": (scenario.n_vehicles,) * 2,
            "cav_penetration": (scenario.cav_penetration,) * 2,
            "style_mix": (scenario.style_mix,) if isinstance(scenario.style_mix, str) else (),
            "style_preset": (style_preset,),
            "kind": (scenario.kind,),
            "inflow_vph": (getattr(scenario, "inflow_vph", _DEFAULT_INFLOW_VPH),) * 2,
            "backends": (backend,),
        }
        default = Scenario()
        defaults = {
            "n_vehicles": (default.n_vehicles,) * 2,
            "cav_penetration": (default.cav_penetration,) * 2,
            "style_mix": (default.style_mix,),
            "style_preset": (SimConfig().style_preset,),
            "kind": (default.kind,),
            "inflow_vph": (_DEFAULT_INFLOW_VPH,) * 2,
            "backends": (EnvConfig().backend,),
        }
        filled: dict[str, Any] = {}
        for name, value in own.items():
            given = getattr(self, name)
            if not given:
                if not value:
                    raise ConfigError(
                        f"mix.{name}: the run's own is a custom style mix; list names in mix"
                    )
                filled[name] = value
            elif value != defaults[name] and given != value:  # (equal: filled before)
                where = _RUN_FIELD.get(name, f"env.scenario.{name}")
                raise ConfigError(
                    f"mix.{name} and {where} ({value[0]!r}) are both set; the mix sets "
                    f"{name}: leave {where} at its default or drop mix.{name}"
                )
        return dataclasses.replace(self, **filled)

    def map_names(self) -> tuple[str, ...]:
        """Every map a block may draw: ``maps``, then the generated ones."""
        generated = generated_names("train", self.generated_maps) if self.generated_maps else []
        return (*self.maps, *generated)


def cell_scenario(
    base: Scenario,
    kind: str,
    cav_penetration: float,
    style_mix: str,
    n_vehicles: int,
    inflow_vph: float,
    demand_s: float,
) -> Scenario:
    """``base`` (``env.scenario``) with a cell's draws: a release of ``n_vehicles``, or a
    demand of ``inflow_vph`` over ``demand_s`` with an agent slot for every CAV."""
    shared = {"cav_penetration": cav_penetration, "style_mix": style_mix}
    if kind == "release":
        return base.replace(kind="release", n_vehicles=n_vehicles, **shared)
    return base.replace(
        kind="demand", inflow_vph=inflow_vph, demand_s=demand_s, cav_slots=EVERY_CAV, **shared
    )


def corner_scenarios(mix: MixConfig, base: Scenario) -> list[Scenario]:
    """The scenarios at the low and high ends of every kind the mix draws: the fewest
    and the most vehicles and CAVs any of its cells has (counts grow with N, inflow and
    the CAV share)."""
    corners = []
    for kind in dict.fromkeys(mix.kind):
        for end in (0, 1):
            corners.append(
                cell_scenario(
                    base,
                    kind,
                    mix.cav_penetration[end],
                    mix.style_mix[0],
                    mix.n_vehicles[end],
                    mix.inflow_vph[end],
                    mix.demand_s,
                )
            )
    return corners
