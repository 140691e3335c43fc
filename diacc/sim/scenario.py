"""Vehicle population: how many vehicles, which are CAVs, which style, where.

A :class:`Scenario` is the *what* (N, penetration, style mix); a
:class:`Population` is the seeded *draw*: one array entry per vehicle with
its type, style and starting slot. Both backends insert exactly the same
population, which is what makes cross-backend comparisons meaningful.

Two kinds of scenario (``Scenario.kind``):

* ``"release"`` (the paper's, the default): all vehicles start at t = 0 near
  the route start at ``insert_speed_mps``, one every ``insert_spacing_m``
  (8 m: 25 vehicles fill the first 200 m, a start that gives paper-like
  congestion; the paper gives no coordinates), lanes taken round-robin in a
  random order, vehicles shuffled over the slots.
* ``"demand"``: vehicles enter at ``insert_start_m`` over ``demand_s``
  seconds at ``inflow_vph`` (one per 3600 / inflow s, each at a uniformly
  drawn instant within its own interval, so the arrival rate is exact and
  the sequence still irregular; the first vehicle is a CAV at t = 0), same
  round-robin lanes, same CAV share and style mix. ``n_vehicles`` is then
  derived: inflow x duration. A vehicle is *pending* (neither active nor
  arrived) until it departs; a backend inserts it at its departure time
  once its lane's entry is free, so a queue at the entry delays it but
  never drops it.

The two kinds are two types, ``Scenario = Release | Demand``: a release has no
demand settings and a demand no ``n_vehicles`` field (its count is a property,
inflow x duration). ``Scenario(kind=..., **settings)`` builds the one ``kind``
names and never overwrites a setting: a demand given an ``n_vehicles`` other than
the one its inflow and duration make, or a release given demand settings other
than their defaults (``inflow_vph``, ``demand_s``, ``cav_slots``), is a one-line
:class:`ScenarioError`. :meth:`Release.replace` / :meth:`Demand.replace` change
settings (the kind too) and derive the count again.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from diacc.fields import (
    MAX_INFLOW_VPH,
    MAX_VEHICLES,
    VEHICLES_WHY,
    ConfigError,
    FieldError,
    check_fields,
    one_of,
    ranged,
)
from diacc.sim.maps import Map

STYLE_NAMES = ("aggressive", "normal", "cautious")
AGGRESSIVE, NORMAL, CAUTIOUS = 0, 1, 2
#: Style code stored in ``TrafficState.style`` for CAVs.
CAV_STYLE = -1
#: HDV style mixes (aggressive, normal, cautious), paper Table I.
STYLE_MIXES: dict[str, tuple[float, float, float]] = {
    "D1": (0.2, 0.6, 0.2),
    "D2": (0.2, 0.4, 0.4),
    "D3": (0.4, 0.4, 0.2),
}


#: How vehicles enter (module docstring).
SCENARIO_KINDS = ("release", "demand")
_INFLOW_WHY = "more than 4 lanes carry"
#: ``Demand.cav_slots`` (the default) that gives every CAV of the episode an agent slot.
EVERY_CAV = "every"


def cav_slots_value(value: int | str) -> int | str:
    """``Demand.cav_slots`` from user input: ``"every"``, or a cap given as an int or as
    its text (``--set env.scenario.cav_slots=16``, ``--agent-slots 16``); anything else
    is passed on for :class:`Demand` to refuse in one line."""
    if isinstance(value, str) and value.strip().isdigit():
        return int(value)
    return value


class ScenarioError(ConfigError):
    """Scenario settings that contradict each other (a field's own range is a
    :class:`~diacc.fields.FieldError`); the message is one line."""


class _ScenarioType(type):
    """``isinstance(x, Scenario)``: x is a :class:`Release` or a :class:`Demand`."""

    def __instancecheck__(cls, obj: object) -> bool:
        return isinstance(obj, _Traffic)


class Scenario(metaclass=_ScenarioType):
    """What traffic to simulate: ``Release | Demand``. ``Scenario(kind=..., **settings)``
    builds the one ``kind`` names (default ``"release"``), refusing what it would
    otherwise overwrite or ignore (one-line :class:`ScenarioError`)."""

    if TYPE_CHECKING:
        # The checker's view of ``Release | Demand``: what code reading a scenario may
        # ask of either kind (the demand settings are read after ``kind == "demand"``).
        # Nothing here exists at run time.
        __dataclass_fields__: ClassVar[dict[str, Any]]  # both kinds are dataclasses
        kind: str
        cav_penetration: float
        style_mix: str | tuple[float, float, float]
        insert_start_m: float
        insert_spacing_m: float
        insert_speed_mps: float
        warmup_s: float
        cav_slot_style: str
        inflow_vph: float
        demand_s: float
        cav_slots: int | str

        @property
        def n_vehicles(self) -> int: ...
        @property
        def n_slots(self) -> int: ...
        @property
        def n_cav_slots(self) -> int: ...
        @property
        def n_cavs(self) -> int: ...
        @property
        def mix(self) -> tuple[float, float, float]: ...
        def replace(self, **changes: Any) -> Release | Demand: ...
        def with_a_slot_per_cav(self) -> Demand: ...

    def __new__(  # type: ignore[misc]
        cls, kind: str = "release", n_vehicles: int | None = None, **settings
    ) -> Release | Demand:
        if kind not in SCENARIO_KINDS:
            names = ", ".join(SCENARIO_KINDS)
            raise FieldError("kind", f"must be one of {names}, got {kind!r}")
        if kind == "release":
            for name in _DEMAND_ONLY:
                value = settings.pop(name, _DEMAND_DEFAULTS[name])
                if value != _DEMAND_DEFAULTS[name]:
                    raise ScenarioError(
                        f"{name} {value!r} is a demand setting; a release (kind 'release') "
                        f"ignores it: set kind 'demand' or leave {name} at "
                        f"{_DEMAND_DEFAULTS[name]!r}"
                    )
            count: dict[str, Any] = {} if n_vehicles is None else {"n_vehicles": n_vehicles}
            return Release(**settings, **count)
        demand = Demand(**settings)
        if n_vehicles is not None and n_vehicles != demand.n_vehicles:
            raise ScenarioError(
                f"n_vehicles {n_vehicles!r} contradicts the demand: inflow_vph "
                f"{demand.inflow_vph:g} x demand_s {demand.demand_s:g} s makes "
                f"{demand.n_vehicles} vehicles; a demand scenario derives its count, "
                "leave n_vehicles out"
            )
        return demand

    @staticmethod
    def with_cavs(n_vehicles: int, n_cavs: int, **kwargs) -> Release:
        """A release with an exact CAV count (checked against ``n_vehicles``)."""
        if n_cavs > n_vehicles:
            raise ScenarioError(f"{n_cavs} CAVs requested but only {n_vehicles} vehicles")
        if n_cavs < 0:
            raise ScenarioError(f"n_cavs must be >= 0, got {n_cavs}")
        return Release(n_vehicles=n_vehicles, cav_penetration=n_cavs / n_vehicles, **kwargs)


# The checker sees both kinds as Scenarios; at run time ``isinstance`` says so
# (``_ScenarioType``) and the kinds derive from nothing.
if TYPE_CHECKING:
    _Kind = Scenario
else:
    _Kind = object


@dataclass(frozen=True)
class _Traffic(_Kind):
    """The settings both kinds share (the seed is given to ``Backend.reset``)."""

    cav_penetration: float = ranged(0.4, 0, 1)  # paper training cell: 10 of 25 CAVs,
    style_mix: str | tuple[float, float, float] = "D1"  # HDV styles of mix D1
    insert_start_m: float = 10.0  # x of the rearmost insertion row
    insert_spacing_m: float = ranged(8.0, 0, open_low=True)  # between consecutive vehicles
    insert_speed_mps: float = ranged(10.0, 0)
    warmup_s: float = ranged(0.0, 0)  # metrics ignore states before this time (traffic settles)
    #: ``""``: the CAV slots hold CAVs. A style name (:data:`STYLE_NAMES`): the
    #: same slots hold HDVs of that style instead (the ``same-mix`` baseline),
    #: so the draw keeps every other vehicle's style and every vehicle's slot and
    #: a comparison isolates what the CAVs' control changes.
    cav_slot_style: str = one_of("", ("", *STYLE_NAMES))

    def __post_init__(self) -> None:
        check_fields(self)
        mix = self.mix
        if len(mix) != 3 or any(p < 0 for p in mix) or abs(sum(mix) - 1.0) > 1e-6:
            raise ScenarioError(
                f"style_mix must be 3 non-negative shares (aggressive, normal, cautious) "
                f"summing to 1, got {self.style_mix!r}"
            )

    def replace(self, **changes) -> Release | Demand:
        """A scenario with ``changes`` (``kind`` among them, or not): a demand's count
        is derived again, and, when the kind changes, the other kind's settings return
        to their defaults unless given.

        :func:`diacc.config.override` rebuilds scenarios with it, so that
        ``--set env.scenario.inflow_vph=3600`` on a demand scenario is not refused as
        contradicting the count its old inflow made.
        """
        kind = changes.pop("kind", self.kind)
        own = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.init}
        if kind != self.kind:
            own = {name: value for name, value in own.items() if name in _SHARED}
        return Scenario(kind=kind, **{**own, **changes})

    @property
    def mix(self) -> tuple[float, float, float]:
        if isinstance(self.style_mix, str):
            if self.style_mix not in STYLE_MIXES:
                raise ScenarioError(
                    f"unknown style mix {self.style_mix!r}; known: {', '.join(STYLE_MIXES)}"
                )
            return STYLE_MIXES[self.style_mix]
        return tuple(float(p) for p in self.style_mix)  # type: ignore[return-value]

    @property
    def n_cav_slots(self) -> int:
        """Vehicles drawn into CAV slots (CAVs, or HDVs of ``cav_slot_style``)."""
        return int(round(self.cav_penetration * self.n_vehicles))

    @property
    def n_cavs(self) -> int:
        """CAVs on the road over the whole episode (0 when the slots hold humans)."""
        return 0 if self.cav_slot_style else self.n_cav_slots


@dataclass(frozen=True)
class Release(_Traffic):
    """The paper's scenario: every vehicle starts at t = 0 (module docstring)."""

    n_vehicles: int = ranged(25, 1, MAX_VEHICLES, why=VEHICLES_WHY)  # paper training cell
    kind: str = dataclasses.field(default="release", init=False)

    @property
    def n_slots(self) -> int:
        """Agent slots C: every CAV has its own."""
        return self.n_cavs


@dataclass(frozen=True)
class Demand(_Traffic):
    """Vehicles enter at ``inflow_vph`` for ``demand_s`` seconds (module docstring)."""

    # vehicles per hour entering the route
    inflow_vph: float = ranged(2400.0, 0, MAX_INFLOW_VPH, open_low=True, why=_INFLOW_WHY)
    demand_s: float = ranged(300.0, 0, open_low=True)  # vehicles enter during [0, demand_s)
    # agent slots: "every" CAV of the episode its own (none drives itself), or a cap on
    # the CAVs the policy drives at once (a CAV that finds every slot taken drives itself)
    cav_slots: int | str = EVERY_CAV
    kind: str = dataclasses.field(default="demand", init=False)

    def with_a_slot_per_cav(self) -> Demand:
        """This demand with an agent slot for every CAV of the episode: none drives itself."""
        return dataclasses.replace(self, cav_slots=EVERY_CAV)

    def __post_init__(self) -> None:
        slots = self.cav_slots
        if slots != EVERY_CAV and (
            isinstance(slots, bool) or not isinstance(slots, int) or not 1 <= slots <= MAX_VEHICLES
        ):
            raise FieldError(
                "cav_slots",
                f"must be {EVERY_CAV!r} or an integer in [1, {MAX_VEHICLES}], got {slots!r} "
                "(no scenario holds more vehicles)",
            )
        super().__post_init__()
        if self.warmup_s >= self.demand_s:
            raise ScenarioError(
                f"demand_s must be longer than warmup_s, got demand_s "
                f"{self.demand_s!r}, warmup_s {self.warmup_s!r}"
            )
        n_total = self.inflow_vph * self.demand_s / 3600.0
        if not n_total <= MAX_VEHICLES:
            raise ScenarioError(
                f"demand_s {self.demand_s!r} s at inflow_vph {self.inflow_vph:g} makes "
                f"{n_total:.3g} vehicles; at most {MAX_VEHICLES} "
                f"(demand_s <= {3600.0 * MAX_VEHICLES / self.inflow_vph:g} s: {VEHICLES_WHY})"
            )

    @property
    def n_vehicles(self) -> int:
        """Vehicles of the whole demand: one per 3600 / inflow seconds."""
        return max(1, int(self.inflow_vph * self.demand_s / 3600.0))

    @property
    def n_slots(self) -> int:
        """Agent slots C: with ``cav_slots = "every"`` one per CAV of the episode, so
        that none ever waits for a slot (each CAV holds at most one, and there are as
        many slots as CAVs); with a cap, at most ``cav_slots`` CAVs at once, a slot
        reused when its CAV leaves (:class:`diacc.envs.env.BottleneckEnv`).

        A slot per CAV of the whole episode, not per CAV on the road at once: on
        ``train-50`` at jam spacing (~7.5 m) some 600 vehicles fit on the road, more
        than the 480 of a 3600 veh/h x 480 s run, so no tighter bound holds for every
        backend and seed. The slots of CAVs not yet entered or gone are dead: masked in
        every loss, and the PPO update skips their sequences
        (:func:`diacc.learn.buffer.make_batch`), so they cost rollout memory only
        (docs/concepts/scenarios.md, "Agent slots").
        """
        if self.cav_slots == EVERY_CAV:
            return self.n_cavs
        return min(int(self.cav_slots), self.n_cavs)


#: A release's vehicle count when none is given (the paper's training cell).
RELEASE_VEHICLES = 25
#: Settings only a demand scenario has; a release refuses values other than these.
_DEMAND_ONLY = ("inflow_vph", "demand_s", "cav_slots")
_DEMAND_DEFAULTS = {f.name: f.default for f in dataclasses.fields(Demand) if f.name in _DEMAND_ONLY}
#: Settings both kinds have.
_SHARED = {f.name for f in dataclasses.fields(_Traffic)}
#: Every key a scenario takes, with its default (``n_vehicles``: a release's).
SCENARIO_SETTINGS = {
    **{f.name: f.default for f in dataclasses.fields(_Traffic)},
    "n_vehicles": RELEASE_VEHICLES,
    "kind": "release",
    **_DEMAND_DEFAULTS,
}


@dataclass(frozen=True)
class Population:
    """One seeded draw of a scenario on a map: arrays of shape (V,)."""

    is_cav: np.ndarray  # (V,) bool
    style: np.ndarray  # (V,) int8, CAV_STYLE for CAVs
    x_m: np.ndarray  # (V,) float64 initial centre position
    lane: np.ndarray  # (V,) int16 initial absolute lane
    speed_mps: np.ndarray  # (V,) float64 initial speed
    depart_s: np.ndarray  # (V,) float64 departure time: all 0 in a release, increasing in demand

    @property
    def n_vehicles(self) -> int:
        return int(self.is_cav.shape[0])


def draw_population(scenario: Scenario, road: Map, seed: int) -> Population:
    """Draw types, styles and starting slots for every vehicle, reproducibly."""
    rng = np.random.default_rng(seed)
    n, n_cav = scenario.n_vehicles, scenario.n_cav_slots
    lanes = list(road.lane_range(0))
    if not lanes:  # pragma: no cover - maps always have >= 1 lane
        raise ScenarioError(f"map {road.name!r} has no lane at its start")

    # Styles for HDVs: largest-remainder rounding of the mix, then shuffled.
    n_hdv = n - n_cav
    shares = np.array(scenario.mix) * n_hdv
    counts = np.floor(shares).astype(int)
    for k in np.argsort(-(shares - counts))[: n_hdv - counts.sum()]:
        counts[k] += 1
    hdv_styles = np.repeat(np.arange(3, dtype=np.int8), counts)
    style = np.concatenate([np.full(n_cav, CAV_STYLE, np.int8), hdv_styles])
    is_cav = np.arange(n) < n_cav
    order = rng.permutation(n)
    style, is_cav = style[order], is_cav[order]
    if scenario.kind == "demand" and is_cav.any():
        # The first vehicle to enter is a CAV (slot), so that every episode starts
        # with an agent (PettingZoo); the draw stays as it was otherwise.
        first_cav = int(np.argmax(is_cav))
        for arr in (is_cav, style):
            arr[[0, first_cav]] = arr[[first_cav, 0]]
    if scenario.cav_slot_style:  # same draws, the slots driven by humans
        style[is_cav] = STYLE_NAMES.index(scenario.cav_slot_style)
        is_cav[:] = False

    lane_order = rng.permutation(lanes)
    lane = lane_order[np.arange(n) % len(lanes)].astype(np.int16)
    if scenario.kind == "demand":
        # Arrival k at a uniform instant of its own interval [k, k + 1) * headway: exact
        # rate, irregular sequence; everyone enters at the route start, lanes round-robin.
        headway_s = 3600.0 / scenario.inflow_vph
        depart_s = (np.arange(n) + rng.uniform(0.0, 1.0, n)) * headway_s
        depart_s[0] = 0.0  # the first vehicle (a CAV, above) enters at t = 0
        return Population(
            is_cav=is_cav,
            style=style,
            x_m=np.full(n, scenario.insert_start_m),
            lane=lane,
            speed_mps=np.full(n, scenario.insert_speed_mps, dtype=np.float64),
            depart_s=depart_s,
        )

    # Slots: one vehicle every ``insert_spacing_m``, lanes round-robin,
    # so vehicles in the same lane start n_lanes * spacing apart. The lane order
    # of the round-robin is drawn at random; vehicles are shuffled over slots.
    x = scenario.insert_start_m + scenario.insert_spacing_m * np.arange(n - 1, -1, -1.0)
    if x[0] >= road.segments[0].length_m:
        raise ScenarioError(
            f"{n} vehicles do not fit in the first segment of map {road.name!r} "
            f"at {scenario.insert_spacing_m} m spacing"
        )
    return Population(
        is_cav=is_cav,
        style=style,
        x_m=x,
        lane=lane,
        speed_mps=np.full(n, scenario.insert_speed_mps, dtype=np.float64),
        depart_s=np.zeros(n),
    )
