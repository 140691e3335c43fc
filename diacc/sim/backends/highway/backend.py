"""The fast ``highway`` backend: highway-env geometry, vectorised IDM/MOBIL traffic.

Road geometry is a highway-env ``RoadNetwork`` (:mod:`.road`), but the
traffic itself lives in (E, V) NumPy arrays (the typed records of
:mod:`.simstate`), one row per environment of a batch (E = 1 for a single
env), and every sub-step updates all vehicles of all envs at once
(:mod:`.models`): no Python loop over vehicles or envs in ``step``. This
is what makes the backend 100x+ faster than stock multi-agent ``highway-v0``
(``diacc.experiments.bench.highway``).

Modelling choices (documented here because both backends must agree on them):

* **Lane index during a lane change.** A manoeuvre goes from ``lane_from``
  to ``lane_to``; while it lasts the vehicle *occupies both lanes* for car
  following (followers in either lane react to it, it reacts to leaders in
  either lane). The reported ``TrafficState.lane`` switches when the centre
  crosses the lane boundary.
* **Lateral motion** is at constant lateral speed: CAVs complete a commanded
  change in exactly one decision step; HDVs take ``hdv_lane_change_s``.
  ``heading_rad = atan2(v_lat, v_long)`` of the last sub-step, clipped to
  ``max_heading_rad``.
* **HDVs** follow IDM (style parameters, braking clipped at
  ``max_brake_mps2``), reconsider lanes every ``decision_period_s`` with
  MOBIL, and in a lane that ends are forced to merge (see
  :mod:`.models`), except drivers whose style has ``lc_strategic < 0``
  (the ``paper`` presets' cautious drivers): like LC2013 on SUMO they make no
  lane change for the lane end and stop at it. A last-resort guard keeps an HDV behind its HDV
  leader; its use is counted in ``stats["guard_events"]`` (0 in practice).
* **CAVs** follow their commands exactly (see :mod:`diacc.sim.backends.base`);
  one without a command (NaN) drives itself for the step like a cooperative
  CAV (below), and so does a CAV that has just entered, until its first step.
  A commanded change is made only if :meth:`Map.lane_change_allowed` says
  so (the rule PSAR applies too). A CAV is never moved by the simulator: in
  a lane that ends it stops with its front at the end (counted in
  ``stats["cav_lane_end_stops"]`` when it arrives there moving) and may
  change lanes later.
* **HDV lane changes respect CAVs**: MOBIL and the forced merge accept a gap
  in front of a CAV only if the CAV, holding its commanded speed for the
  step and then braking at ``cav.safe_decel_mps2``, stays ``cav.min_gap_m`` behind
  (:func:`diacc.sim.kinematics.safe_gap_m`, the margin PSAR uses); IDM's view
  of the follower would assume it brakes at once.
* **Cooperative CAVs** (``SimConfig.cav_mode="cooperative"``, the paper's non-learning
  "cooperative" baseline; SUMO uses CACC with ``lcCooperative = 1``): CAVs
  ignore the commands and are driven by the same vectorised IDM / MOBIL /
  forced-merge code as HDVs, with a CACC-like parameter set
  (:class:`CooperativeCavParams`: short time headway 0.6 s, minimum gap 1 m,
  the CAV accel/decel limits, MOBIL politeness 1 i.e. fully cooperative lane
  changes). They are still reported as CAVs in the TrafficState.
* **Collisions** are oriented-rectangle overlaps between active vehicles at
  any sub-step. A pair is reported in the step its contact begins. Collided
  vehicles stop where they are and stay on the road as obstacles (as in
  highway-env); the environment ends the episode anyway.
* **Arrival**: a vehicle whose centre passes ``Map.length_m`` becomes
  inactive and is listed in ``arrivals`` of that step.
* **Departure** (``demand`` scenarios): a pending vehicle enters at its
  population slot at the first sub-step at or after its departure time at
  which its entry is free: no vehicle of its lane closer ahead than the
  gap IDM wants at its insertion speed behind that vehicle (s* = s0 + vT +
  v dv / 2 sqrt(ab)), and no earlier vehicle of its lane still waiting
  (first come, first served per lane). SUMO's default insertion checks make
  the same decision with its own car-following model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from diacc.sim.backends.base import BackendError, CavCommands
from diacc.sim.backends.highway.models import (
    HighwayModel,
    IdmParams,
    box_contacts,
    idm_accel,
)
from diacc.sim.backends.highway.road import LaneTables, build_road_network
from diacc.sim.backends.highway.simstate import HighwayCaches, HighwayParams, HighwayState
from diacc.sim.drivers import STYLE_PRESETS
from diacc.sim.kinematics import lane_change_reach_m, safe_gap_m
from diacc.sim.maps import Map
from diacc.sim.scenario import Scenario, draw_population
from diacc.sim.settings import SimConfig
from diacc.sim.state import TrafficState, flat_offsets, take, take_last

_EMPTY_PAIRS = np.zeros((0, 2), dtype=np.int32)


@dataclass(frozen=True)
class CooperativeCavParams:
    """IDM/MOBIL image of a CACC CAV with cooperative lane changes (cooperative baseline).

    The time headway and minimum gap are the CAV vType's (``CavParams``), which
    is also what SUMO's CACC model is given on the ``sumo`` backend, so the
    baseline means the same on both; politeness 1 weighs the followers' gain as
    much as the own (SUMO's ``lcCooperative = 1``). Acceleration limits are the
    CAVs' (``SimConfig.cav``).
    """

    time_headway_s: float = 1.0
    min_gap_m: float = 1.0
    politeness: float = 1.0
    lc_gain_threshold_mps2: float = 0.1


def _rows_where(mask: np.ndarray, new: np.ndarray, old: np.ndarray) -> np.ndarray:
    """``new`` in the envs of the (E,) ``mask``, ``old`` elsewhere (any trailing shape)."""
    return np.where(mask.reshape((-1,) + (1,) * (new.ndim - 1)), new, old)


class HighwayBackend:
    """Vectorised highway traffic on a highway-env road (see module docstring).

    One object simulates ``n_envs`` environments of the same map and
    scenario, each its own block of (V,) rows in (E, V) arrays: every sub-step
    updates all vehicles of all envs at once, and nothing couples two envs.
    The :class:`~diacc.sim.backends.base.Backend` methods :meth:`reset` and
    :meth:`step` are the E = 1 case; a batch is reset env by env
    (:meth:`reset_env`) and stepped together (:meth:`step_batch`), with the
    same results per env as E separate backends (``tests/test_highway_batch.py``).

    The arrays are three records (:mod:`.simstate`), created at the first
    reset: :attr:`state` (what a step changes), :attr:`params` (per-vehicle
    parameters fixed at reset) and :attr:`caches` (derived quantities kept
    between sub-steps). Copies of the three and of :attr:`stats` put a batch
    back exactly where it was (``tests/test_highway_simstate.py``).

    Work that the single-env simulator skips when nothing happened (leader
    search, lane-change decisions, the exact box test) is skipped only when
    it is a no-op for every env; where some envs need it, its results are
    kept for those envs alone (:func:`_rows_where`), so skipping stays
    invisible in the results.

    A demand episode holds every vehicle of the episode (hundreds) while a few
    dozen are on the road, so a step moves only the index window of vehicles
    that are not settled (:meth:`_window`: not long arrived, not still to
    come), the union over the envs; the results are those of stepping all,
    bit for bit (``tests/test_highway_window.py``).
    """

    name = "highway"
    #: diacc's own NumPy dynamics, versioned with diacc (results record "").
    version = ""
    #: Many envs step fastest as rows of one batch (:class:`diacc.envs.vector.BatchedVectorEnv`);
    #: worker processes would only add pickling.
    vector_mode = "batched"
    #: Step only the index window of vehicles not settled (:meth:`_window`): the same
    #: results as stepping all; False steps every vehicle (tests compare the two).
    windowed = True
    #: Batches of fewer vehicles per env always step all (the window would gain little).
    window_min_vehicles = 64

    def __init__(
        self,
        road: Map,
        sim: SimConfig,
        model: HighwayModel | None = None,
        cooperative: CooperativeCavParams | None = None,
        n_envs: int = 1,
    ) -> None:
        self.cav_mode = sim.cav_mode
        self.cooperative = cooperative or CooperativeCavParams()
        self.road = road
        self.sim = sim
        self.model = model or HighwayModel()
        self.n_envs = n_envs
        self.network = build_road_network(road)
        self.tables = LaneTables.from_map(road)
        self.dt_s = sim.step_s / sim.substeps
        self._decide_every = max(1, int(round(self.model.decision_period_s / self.dt_s)))
        self._ready = np.zeros(n_envs, dtype=bool)  # (E,) env has been reset
        #: Per-env event counters, each (E,) int64.
        self.stats: dict[str, np.ndarray] = {
            key: np.zeros(n_envs, np.int64)
            for key in ("guard_events", "forced_merges", "mobil_changes", "cav_lane_end_stops")
        }

    # ------------------------------------------------------------------ API
    def reset(self, scenario: Scenario, seed: int) -> TrafficState:
        """Insert ``draw_population(scenario, road, seed)`` and return the t = 0 state (E = 1)."""
        self._check_single()
        return self.reset_env(0, scenario, seed)

    def step(self, commands: CavCommands) -> TrafficState:
        """Advance one decision step (``sim.substeps`` integration sub-steps); E = 1."""
        self._check_single()
        batch = CavCommands(
            np.asarray(commands.lane_change)[None], np.asarray(commands.speed_change_mps)[None]
        )
        return self.step_batch(batch)[0]

    def close(self) -> None:
        """Nothing to release: the simulation is arrays in this process."""

    def reset_env(self, env: int, scenario: Scenario, seed: int) -> TrafficState:
        """Start env ``env`` of the batch anew with ``draw_population(scenario, road, seed)``.

        The other envs are untouched. Every env must be reset once before the
        first :meth:`step_batch`; all envs carry the same number of vehicles.
        """
        pop = draw_population(scenario, self.road, seed)
        n = pop.n_vehicles
        if not self._ready.any():
            self._allocate(n)
        elif n != self.state.x_m.shape[1]:
            raise BackendError(f"env {env} has {n} vehicles, the batch {self.state.x_m.shape[1]}")
        styles = STYLE_PRESETS[self.sim.style_preset]
        cav = self.sim.cav
        coop = self.cav_mode == "cooperative"
        headway_s = self.cooperative.time_headway_s if coop else cav.time_headway_s
        min_gap_m = self.cooperative.min_gap_m if coop else cav.min_gap_m
        hdv_style = np.where(pop.is_cav, 0, pop.style).astype(np.intp)

        def per_vehicle(attr: str, cav_value: float) -> np.ndarray:
            table = np.array([getattr(s, attr) for s in styles])
            return np.where(pop.is_cav, cav_value, table[hdv_style])

        def row(value, dtype: type = np.float64) -> np.ndarray:
            """``value`` (a scalar or (V,)) as an E = 1 row of ``dtype``."""
            return np.broadcast_to(np.asarray(value, dtype), (n,))[None].copy()

        idm = IdmParams(
            row(per_vehicle("time_headway_s", headway_s)),
            row(per_vehicle("min_gap_m", min_gap_m)),
            row(per_vehicle("accel_mps2", cav.accel_mps2)),
            row(per_vehicle("decel_mps2", cav.decel_mps2)),
            self.sim.idm_delta,
        )
        # A late merger (DriverStyle.merge_zone_m) is forced to merge only that close to the end.
        zones = [
            self.model.merge_zone_m if s.merge_zone_m is None else s.merge_zone_m for s in styles
        ]
        params = HighwayParams(
            idm=idm,
            inv_2_sqrt_ab_s2_per_m=0.5 / np.sqrt(idm.accel_mps2 * idm.decel_mps2),
            # CAVs that drive themselves (cooperative mode, or no command) change lanes
            # cooperatively; commanded CAVs never run MOBIL.
            politeness=row(per_vehicle("politeness", self.cooperative.politeness)),
            gain_threshold_mps2=row(
                per_vehicle("lc_gain_threshold_mps2", self.cooperative.lc_gain_threshold_mps2)
            ),
            # LC2013's lcStrategic < 0 (the authors' cautious drivers): no lane change
            # because a lane ends, so such a driver stops at the end of its lane.
            strategic=row(per_vehicle("lc_strategic", 0.0) >= 0.0, bool),
            zipper=row(per_vehicle("zipper", False), bool),
            merge_zone_m=row(
                np.where(pop.is_cav, self.model.merge_zone_m, np.array(zones)[hdv_style])
            ),
            reported_cav=row(pop.is_cav, bool),
            style=row(pop.style, np.int8),
            depart_s=row(pop.depart_s),
        )
        pending = row(pop.depart_s > 0.0, bool)
        speed_mps = row(pop.speed_mps)
        state = HighwayState(
            x_m=row(pop.x_m),
            y_m=row(self.road.lane_center_y_m(pop.lane)),
            speed_mps=speed_mps,
            lat_speed_mps=row(0.0),
            heading_rad=row(0.0),
            cooldown_s=row(0.0),
            lane_from=row(pop.lane, np.intp),
            lane_to=row(pop.lane, np.intp),
            active=~pending,
            arrived=row(False, bool),
            crashed=row(False, bool),
            pending=pending,
            # Vehicles driven by commands; cooperative CAVs drive like HDVs.
            is_cav=row(False if coop else pop.is_cav, bool),
            yield_to=row(-1, np.intp),
            route_end_m=row(self.road.length_m),
            cav_target_mps=speed_mps.copy(),
            cav_accel_mps2=row(0.0),
            contact=np.zeros((1, n, n), bool),
            time_s=np.zeros(1),
            step_count=np.zeros(1, np.int64),
        )
        self.params.set_env(env, params)
        self.state.set_env(env, state)
        for counts in self.stats.values():
            counts[env] = 0
        self._ready[env] = True
        only = np.arange(self.n_envs) == env  # (E,)
        self.caches.leaders_dirty[env] = True
        self._refresh_road_facts(only)
        self._refresh_speed_bounds()
        lane = self._lane()
        return self._make_state(env, lane, np.zeros(n), _EMPTY_PAIRS, np.zeros(0, np.int32))

    def _insert_due(self, now_s: np.ndarray) -> None:
        """Let pending vehicles whose departure time ``now_s`` (E,) has come enter where
        their lane's entry is free (module docstring, "Departure")."""
        state, params, caches = self.state, self.params, self.caches
        due = state.pending & (params.depart_s <= now_s[:, None] + 1e-9)  # (E, V)
        if not due.any():
            return
        length_m = self.sim.vehicle_length_m
        entered = np.zeros_like(due)
        for e in np.flatnonzero(due.any(axis=1)):
            waiting = state.pending[e]
            for lane in np.unique(state.lane_to[e, due[e]]):
                # First come, first served per lane.
                first = np.flatnonzero(waiting & (state.lane_to[e] == lane))[0]
                if not due[e, first]:
                    continue
                x0, v0 = state.x_m[e, first], state.speed_mps[e, first]
                in_lane = state.active[e] & (
                    (state.lane_from[e] == lane) | (state.lane_to[e] == lane)
                )
                ahead = in_lane & (state.x_m[e] > x0 - length_m)
                if ahead.any():
                    j = np.flatnonzero(ahead)[np.argmin(state.x_m[e, ahead])]
                    gap_m = state.x_m[e, j] - x0 - length_m
                    need_m = params.idm.min_gap_m[e, first] + max(
                        0.0,
                        v0 * params.idm.headway_s[e, first]
                        + v0
                        * (v0 - state.speed_mps[e, j])
                        * params.inv_2_sqrt_ab_s2_per_m[e, first],
                    )
                    if gap_m < need_m:
                        continue
                entered[e, first] = True
        if not entered.any():
            return
        state.pending &= ~entered
        state.active |= entered
        state.is_cav &= ~entered  # a CAV drives itself until its first command
        state.cav_target_mps = np.where(entered, state.speed_mps, state.cav_target_mps)
        envs = entered.any(axis=1)
        caches.leaders_dirty |= envs
        self._refresh_road_facts(envs)
        self._refresh_speed_bounds()

    def step_batch(self, commands: CavCommands) -> list[TrafficState]:
        """Advance every env one decision step; ``commands`` arrays are (E, V); a state per env."""
        batch = self.step_stacked(commands)
        return [batch.env(e) for e in range(self.n_envs)]

    def step_stacked(self, commands: CavCommands) -> TrafficState:
        """Advance every env one decision step; ``commands`` arrays are (E, V); one (E, V)
        batch state (:mod:`diacc.sim.state`), what :class:`diacc.envs.batch.EnvBatch` steps on."""
        state, params, caches = self.state, self.params, self.caches
        if not self._ready.all():
            raise BackendError("step before every env of the batch was reset")
        shape = state.x_m.shape
        lane_cmd = np.asarray(commands.lane_change)
        dv_cmd = np.asarray(commands.speed_change_mps, dtype=np.float64)
        if lane_cmd.shape != shape or dv_cmd.shape != shape:
            raise BackendError(
                f"commands must have shape {shape}, got {lane_cmd.shape} and {dv_cmd.shape}"
            )
        speed_start = state.speed_mps.copy()
        if self.cav_mode == "commanded":
            # NaN: no command, the CAV drives itself this step (diacc.sim.backends.base).
            # Over all vehicles (cheap), so the leader refreshes are those of a full step.
            commanded = (state.is_cav | params.reported_cav) & ~np.isnan(dv_cmd)  # (E, V)
            caches.leaders_dirty |= (commanded != state.is_cav).any(axis=1)
            state.is_cav = commanded
            dv_cmd = np.where(commanded, dv_cmd, 0.0)
        arrived_before = state.arrived.copy()
        lo, hi = self._window()
        if (lo, hi) == (0, shape[1]):
            new_contacts = self._step_vehicles(lane_cmd.astype(np.intp), dv_cmd)  # (E, V, V)
        else:
            new_contacts = self._step_window(lo, hi, lane_cmd.astype(np.intp), dv_cmd)
        state.time_s += self.sim.step_s
        state.step_count += 1
        accel = (state.speed_mps - speed_start) / self.sim.step_s  # (E, V)
        new_arrivals = state.arrived & ~arrived_before  # (E, V)
        contacts = (
            np.argwhere(new_contacts).astype(np.int32).reshape(-1, 3)
            if new_contacts.any()
            else np.zeros((0, 3), np.int32)
        )  # (K, 3) env, i, j
        contacts[:, 1:] += lo
        return self._make_batch_state(
            accel, contacts, np.argwhere(new_arrivals).astype(np.int32).reshape(-1, 2)
        )

    def _step_vehicles(self, lane_cmd: np.ndarray, dv_cmd: np.ndarray) -> np.ndarray:
        """The sub-steps of a decision step for the vehicles of :attr:`state` (all of them,
        or the window :meth:`_step_window` put there); commands are (E, V).

        Returns the (E, V, V) contacts that began during the step.
        """
        state = self.state
        self._apply_cav_commands(lane_cmd, dv_cmd)
        new_contacts = np.zeros_like(state.contact)  # (E, V, V)
        demand = state.pending.any()
        for k in range(self.sim.substeps):
            if demand:
                self._insert_due(state.time_s + k * self.dt_s)
            if k % self._decide_every == 0:
                self._decide_lane_changes()
            contact = self._substep()
            if contact is not self._no_contact:  # else no contact begins
                new_contacts |= contact & ~state.contact
            state.contact = contact
        return new_contacts

    def _window(self) -> tuple[int, int]:
        """Vehicle index window ``lo:hi`` (the union over the envs) that this step must move.

        Outside it every vehicle of every env is *settled*, so a full step
        would leave it exactly as it is: arrived (with its heading already
        zeroed and no merger to yield to, which the next sub-step or decision
        would still change) or waiting to enter later than this step. Demand
        vehicles enter in index order and leave roughly so, which keeps the
        window near the vehicles on the road. ``(0, V)`` when windowing is
        off (:attr:`windowed`), the batch is small (:attr:`window_min_vehicles`)
        or nothing is left to move.
        """
        state = self.state
        n = state.x_m.shape[1]
        if not self.windowed or n < self.window_min_vehicles:
            return 0, n
        step_end_s = state.time_s[:, None] + self.sim.step_s + 1e-9  # (E, 1)
        settled = (state.arrived & (state.heading_rad == 0.0) & (state.yield_to < 0)) | (
            state.pending & (self.params.depart_s > step_end_s)
        )  # (E, V)
        live = ~settled.all(axis=0)  # (V,)
        if not live.any():
            return 0, n
        return int(np.argmax(live)), n - int(np.argmax(live[::-1]))

    def _step_window(
        self, lo: int, hi: int, lane_cmd: np.ndarray, dv_cmd: np.ndarray
    ) -> np.ndarray:
        """:meth:`_step_vehicles` on vehicles ``lo:hi`` alone (:meth:`_window`); the (E, W, W)
        new contacts, indices relative to ``lo``.

        The three records are swapped for windows of themselves for the step,
        vehicle indices held in them (``yield_to``, ``leader``) shifted by
        ``lo``, and the stepped window written back.
        """
        full_state, full_params, full_caches = self.state, self.params, self.caches
        width = hi - lo
        state, caches = full_state.window(lo, hi), full_caches.window(lo, hi)
        state.yield_to = np.where(state.yield_to >= 0, state.yield_to - lo, -1)
        caches.leader = np.clip(caches.leader - lo, 0, width - 1)  # only real ones are read
        # Cached for vehicles that left the window on the road: not a guard or a lane change
        # of theirs now (a full step's leader refresh makes them False off the road).
        caches.guarded = caches.guarded & state.active
        caches.moving = caches.moving & state.active
        self.state, self.params, self.caches = state, full_params.window(lo, hi), caches
        self._set_shape_constants(width)
        try:
            new_contacts = self._step_vehicles(lane_cmd[:, lo:hi], dv_cmd[:, lo:hi])
        finally:
            self.state, self.params, self.caches = full_state, full_params, full_caches
            self._set_shape_constants(full_state.x_m.shape[1])
        state.yield_to = np.where(state.yield_to >= 0, state.yield_to + lo, -1)
        caches.leader = caches.leader + lo
        full_state.put_window(lo, hi, state)
        full_caches.put_window(lo, hi, caches)
        return new_contacts

    # ------------------------------------------------------------ internals
    def _check_single(self) -> None:
        if self.n_envs != 1:
            raise BackendError(
                f"a batch of {self.n_envs} envs is reset with reset_env and stepped with step_batch"
            )

    def _allocate(self, n: int) -> None:
        """The (E, V) records of the batch (every row is written by :meth:`reset_env`)
        and the constants that follow from the batch's shape."""
        n_envs = self.n_envs
        self.state = HighwayState.zeros(n_envs, n)
        self.params = HighwayParams.zeros(n_envs, n, self.sim.idm_delta)
        self.caches = HighwayCaches.zeros(n_envs, n)
        self._shape_constants: dict[int, tuple[np.ndarray, ...]] = {}
        self._set_shape_constants(n)
        self._sides = np.array([-1, 0, 1])
        self._min_accel = -self.model.max_brake_mps2

    def _set_shape_constants(self, n: int) -> None:
        """The constant arrays of a step over ``n`` vehicles per env (all V, or a window)."""
        if n not in self._shape_constants:
            self._shape_constants[n] = (
                np.zeros((self.n_envs, n, n), dtype=bool),  # (E, n, n) no contact
                ~np.eye(n, dtype=bool),  # (n, n) j is not i
                np.broadcast_to(np.arange(n), (self.n_envs, n)),  # (E, n) own vehicle index
            )
        self._no_contact, self._not_self, self._rows = self._shape_constants[n]

    def _segment(self) -> np.ndarray:
        return self.tables.segment_of(self.state.x_m)

    def _apply_cav_commands(self, lane_cmd: np.ndarray, dv_cmd: np.ndarray) -> None:
        """Fix each CAV's acceleration for the step and start commanded lane changes."""
        state = self.state
        seg = self._segment()
        limit = self.tables.speed_limit_mps[seg]
        cav = state.is_cav & state.active & ~state.crashed
        target = np.minimum(np.maximum(state.speed_mps + dv_cmd, 0.0), limit)
        accel = np.clip(
            (target - state.speed_mps) / self.sim.step_s,
            -self.sim.cav.decel_mps2,
            self.sim.cav.accel_mps2,
        )
        state.cav_target_mps = np.where(cav, target, state.speed_mps)
        state.cav_accel_mps2 = np.where(cav, accel, 0.0)
        self._refresh_speed_bounds()

        offset = np.minimum(np.maximum(lane_cmd, -1), 1)
        reach_m = lane_change_reach_m(state.speed_mps, self.sim.step_s, self.sim.vehicle_length_m)
        ok = (
            cav
            & (state.lane_from == state.lane_to)
            & self.road.lane_change_allowed(seg, state.lane_from, offset, state.x_m, reach_m)
        )
        dest_c = np.minimum(np.maximum(state.lane_from + offset, 0), self.road.max_lanes - 1)
        self._start_changes(ok, dest_c, self.sim.step_s)

    def _start_changes(self, start: np.ndarray, dest: np.ndarray, duration_s: float) -> None:
        state, caches = self.state, self.caches
        width = self.road.lane_width_m
        direction = np.sign(dest - state.lane_from)
        state.lane_to = np.where(start, dest, state.lane_to)
        state.lat_speed_mps = np.where(start, direction * width / duration_s, state.lat_speed_mps)
        started = start.any(axis=1)  # (E,)
        if started.any():
            caches.leaders_dirty |= started
            self._refresh_road_facts(started)
            moving = state.active & ~state.crashed & (state.lane_from != state.lane_to)
            caches.moving = _rows_where(started, moving, caches.moving)

    def _decide_lane_changes(self) -> None:
        """MOBIL for HDVs, forced merges for vehicles in ending lanes, yielding followers.

        All vehicles and all three lanes (right, own, left) are evaluated at
        once: one (E, 3, V, V) neighbour search and a single IDM call over every
        acceleration MOBIL needs, stacked as (E, 4, 3, V). An env where no
        vehicle may change lanes gets no change and no yielding from it, as if skipped.
        """
        state, params, caches = self.state, self.params, self.caches
        m, sim, tab = self.model, self.sim, self.tables
        x, v, length = state.x_m, state.speed_mps, sim.vehicle_length_m
        n_envs, n = x.shape
        n_lanes = self.road.max_lanes
        self._refresh_road_facts(np.ones(n_envs, dtype=bool))
        seg = self._segment()
        desired = caches.desired_mps

        idle = state.active & ~state.crashed & (state.lane_from == state.lane_to)
        lane = state.lane_from
        dist_end = tab.end_m[seg, lane] - x  # (E, V)
        merge_dir = tab.merge_dir[seg, lane].astype(np.intp)
        # Only HDVs are forced to merge (a CAV that stays in an ending lane stops at its
        # end), and only drivers with a strategic lane-change term (lcStrategic >= 0).
        near_end = idle & (merge_dir != 0) & (dist_end < params.merge_zone_m)
        forced = near_end & params.strategic & ~state.is_cav
        discretionary = (
            idle
            & ~state.is_cav
            & ~near_end
            & (state.cooldown_s <= 0.0)
            & (v >= m.min_lane_change_speed_mps)
        )
        if not (forced.any() or discretionary.any()):
            yielded = (state.yield_to >= 0).any(axis=1)  # (E,)
            if yielded.any():
                state.yield_to[:] = -1
                caches.leaders_dirty |= yielded
            return

        # Neighbours in the right / own / left lane: (E, 3, V) each.
        lanes3 = lane[:, None, :] + self._sides[None, :, None]  # (E, 3, V)
        lanes3_c = np.minimum(np.maximum(lanes3, 0), n_lanes - 1)
        # [e, side, i, j]: j is on the road in lane ``lanes3[e, side, i]`` (one of the two
        # lanes it occupies while changing lanes), and is not i.
        side_lane = lanes3[..., None]  # (E, 3, V, 1)
        in_lane = (state.lane_from[:, None, None, :] == side_lane) | (
            state.lane_to[:, None, None, :] == side_lane
        )  # (E, 3, V, V)
        in_lane &= self._peers()[:, None]
        dx = x[:, None, :] - x[:, :, None]  # (E, V, V) x_j - x_i
        ahead = np.where(in_lane & (dx >= 0.0)[:, None], dx[:, None], np.inf)  # (E, 3, V, V)
        behind = np.where(in_lane & (dx < 0.0)[:, None], -dx[:, None], np.inf)
        lead = ahead.argmin(axis=3)  # (E, 3, V)
        foll = behind.argmin(axis=3)
        # The gaps to ``lead`` and ``foll`` (inf: none): the minima, read at the argmins.
        lead_gap = take_last(ahead, lead[..., None])[..., 0] - length
        foll_gap = take_last(behind, foll[..., None])[..., 0] - length
        has_foll = np.isfinite(foll_gap)

        # Every IDM acceleration MOBIL needs, in one call: (E, 4, 3, V) =
        # [ego behind lane leader, ego before lane end, follower behind ego,
        #  follower behind lane leader].
        me = np.broadcast_to(self._rows[:, None, :], (n_envs, 3, n))
        ego = np.stack([me, me, foll, foll], axis=1)  # (E, 4, 3, V)
        end_gap = tab.end_m[seg[:, None, :], lanes3_c] - x[:, None, :] - 0.5 * length
        gaps = np.stack([lead_gap, end_gap, foll_gap, foll_gap + lead_gap + length], axis=1)
        lead_v = take(v, lead)  # (E, 3, V)
        v3 = np.broadcast_to(v[:, None, :], (n_envs, 3, n))
        lead_v = np.stack([lead_v, np.zeros_like(lead_v), v3, lead_v], axis=1)
        acc = idm_accel(take(v, ego), take(desired, ego), params.idm.take(ego), gaps, lead_v)
        self_acc = np.minimum(acc[:, 0], acc[:, 1])  # (E, 3, V)
        foll_with_me = np.where(has_foll, acc[:, 2], 0.0)
        foll_without = np.where(has_foll, acc[:, 3], 0.0)

        side = [0, 2]  # rows of the right and left lanes
        dest = lanes3[:, side]  # (E, 2, V)
        dest_c = lanes3_c[:, side]
        seg2 = seg[:, None, :]
        x2 = x[:, None, :]
        valid = (dest >= 0) & (dest < n_lanes) & tab.exists[seg2, dest_c]
        gaps_ok = (lead_gap[:, side] >= m.min_accept_gap_m) & (
            foll_gap[:, side] >= m.min_accept_gap_m
        )
        # A CAV follower holds its commanded speed for the rest of the step and only
        # then brakes (at most at its decel limit): the gap must cover that, not IDM.
        foll2 = foll[:, side]  # (E, 2, V)
        cav_foll = take(state.is_cav, foll2) & has_foll[:, side]
        cav_gap_m = sim.cav.min_gap_m + safe_gap_m(
            take(state.cav_target_mps, foll2),
            v[:, None, :],
            sim.step_s,
            sim.cav.safe_decel_mps2,
        )
        gaps_ok &= ~cav_foll | (foll_gap[:, side] >= cav_gap_m)
        nf_after = foll_with_me[:, side]
        gain = (
            self_acc[:, side]
            - self_acc[:, 1:2]
            + params.politeness[:, None, :]
            * (nf_after - foll_without[:, side] + foll_without[:, 1:2] - foll_with_me[:, 1:2])
        )
        mobil_ok = (
            discretionary[:, None, :]
            & valid
            & (tab.end_m[seg2, dest_c] - x2 > m.merge_zone_m + m.merge_lookahead_m)
            & gaps_ok
            & (nf_after >= -m.mobil_max_imposed_brake_mps2)
            & (gain >= params.gain_threshold_mps2[:, None, :])
        )
        urgency = np.minimum(np.maximum(1.0 - dist_end / params.merge_zone_m, 0.0), 1.0)  # (E, V)
        accept_brake = m.mobil_max_imposed_brake_mps2 + urgency * (
            m.forced_max_imposed_brake_mps2 - m.mobil_max_imposed_brake_mps2
        )
        accept_brake2 = accept_brake[:, None, :]
        is_merge = (
            forced[:, None, :] & valid & (merge_dir[:, None, :] == self._sides[side][None, :, None])
        )  # (E, 2, V)
        forced_ok = (
            is_merge
            & gaps_ok
            & (nf_after >= -accept_brake2)
            & (self_acc[:, side] >= -accept_brake2)
        )
        score = np.where(forced_ok, np.inf, np.where(mobil_ok, gain, -np.inf))  # (E, 2, V)
        start = score.max(axis=1) > -np.inf  # (E, V)
        target = np.where(score.argmax(axis=1) == 0, dest_c[:, 0], dest_c[:, 1])

        # Two vehicles entering the same lane side by side in the same instant
        # would not see each other: keep the front one.
        rear_gap_need = params.idm.min_gap_m + v * params.idm.headway_s  # (E, V)
        clash = (
            start[:, :, None]
            & start[:, None, :]
            & (target[:, :, None] == target[:, None, :])
            & self._not_self
            & (
                np.abs(dx) - length
                < np.maximum(rear_gap_need[:, :, None], rear_gap_need[:, None, :])
            )
            & (x[:, None, :] > x[:, :, None])
        )  # (E, V, V)
        start &= ~clash.any(axis=2)

        self.stats["forced_merges"] += (start & forced).sum(axis=1)
        self.stats["mobil_changes"] += (start & ~forced).sum(axis=1)
        self._start_changes(start, target, m.hdv_lane_change_s)

        # Yielding: the nearest follower in the merge lane treats a waiting merger as leader.
        left = merge_dir > 0  # merging into the left lane (row 2), else the right (row 0)
        nf = np.where(left, foll[:, 2], foll[:, 0])  # (E, V)
        nf_gap = np.where(left, foll_gap[:, 2], foll_gap[:, 0])
        nf_acc = np.where(left, foll_with_me[:, 2], foll_with_me[:, 0])
        # (E, V) the follower lets a merger in (zipper preset).
        zipper = take(params.zipper, nf)
        polite = (take(params.politeness, nf) > 0.0) | (v < m.yield_speed_mps) | zipper
        can_brake = np.where(
            zipper, m.forced_max_imposed_brake_mps2, take(params.idm.decel_mps2, nf)
        )
        waiting = (
            forced
            & ~start
            & (dist_end < m.yield_zone_m)
            & (nf_gap > 0.0)
            & np.isfinite(nf_gap)
            & ~take(state.is_cav, nf)
            & polite
            & (nf_acc >= -can_brake)
        )
        yield_to = np.full_like(state.yield_to, -1)
        for e in np.flatnonzero(waiting.any(axis=1)):  # rare: a merger waits
            mergers = np.flatnonzero(waiting[e])
            order = mergers[np.argsort(-x[e, mergers], kind="stable")]  # nearest written last
            yield_to[e, nf[e, order]] = order
        changed = (yield_to != state.yield_to).any(axis=1)  # (E,)
        state.yield_to = yield_to
        caches.leaders_dirty |= changed

    def _peers(self) -> np.ndarray:
        """(E, V, V) bool: j is another vehicle on the road."""
        return self._not_self & self.state.active[:, None, :]

    def _refresh_road_facts(self, envs: np.ndarray) -> None:
        """Per-vehicle desired speed and end of the destination lane, in the (E,) ``envs``.

        Refreshed at every decision and lane-change start rather than every
        sub-step: both only change at segment boundaries, so a new speed
        limit takes effect at the next decision (<= ``decision_period_s``).
        """
        state, caches = self.state, self.caches
        seg = self._segment()
        desired = self.tables.speed_limit_mps[seg]
        # Lane end as a centre position: the obstacle's rear is at the end itself.
        end_x = self.tables.end_m[seg, state.lane_to] + 0.5 * self.sim.vehicle_length_m
        caches.desired_mps = _rows_where(envs, desired, caches.desired_mps)
        caches.end_x_m = _rows_where(envs, end_x, caches.end_x_m)
        caches.inv_desired_s_per_m = 1.0 / np.maximum(caches.desired_mps, 1e-3)

    def _refresh_speed_bounds(self) -> None:
        """Per-vehicle speed window of a sub-step: [0, inf) for HDVs, up to / down to
        the commanded target for CAVs, frozen for wrecked and arrived vehicles.

        Idempotent between commands (a frozen vehicle keeps its speed), so
        refreshing every env when one needs it changes nothing for the others.
        """
        state, caches = self.state, self.caches
        driving = state.active & ~state.crashed
        up = state.cav_accel_mps2 >= 0.0
        lo = np.where(state.is_cav & ~up, state.cav_target_mps, 0.0)
        hi = np.where(state.is_cav & up, state.cav_target_mps, np.inf)
        caches.v_lo_mps = np.where(driving, lo, state.speed_mps)
        caches.v_hi_mps = np.where(driving, hi, state.speed_mps)
        caches.half_dt_active_s = np.where(state.active, 0.5 * self.dt_s, 0.0)

    def _idm_fast(self, v: np.ndarray, gap_m: np.ndarray, lead_v: np.ndarray) -> np.ndarray:
        """:func:`idm_accel` with per-vehicle constants folded in (the sub-step hot path)."""
        params, caches = self.params, self.caches
        p = params.idm
        free = np.power(v * caches.inv_desired_s_per_m, p.delta)
        dynamic = v * (p.headway_s + (v - lead_v) * params.inv_2_sqrt_ab_s2_per_m)
        s_star = p.min_gap_m + np.maximum(dynamic, 0.0)
        ratio = s_star / np.maximum(gap_m, 1e-2)
        return p.accel_mps2 * (1.0 - free - ratio * ratio)

    def _refresh_leaders(self) -> None:
        """Leader of every vehicle in the envs marked dirty: nearest active vehicle
        ahead sharing a lane.

        (A merger a vehicle yields to is a second leader, handled in the sub-step.)

        Leaders only change when a lane change starts or ends, a vehicle
        arrives or crashes, or yielding changes (vehicles in a shared lane
        cannot pass each other without a collision), so the (V, V) search runs
        on those events only and sub-steps reuse the result.
        """
        state, caches = self.state, self.caches
        rows = np.flatnonzero(caches.leaders_dirty)  # (R,) the envs to search again
        every = len(rows) == self.n_envs
        pick = (lambda a: a) if every else (lambda a: a[rows])  # noqa: E731
        x, lf, lt = pick(state.x_m), pick(state.lane_from), pick(state.lane_to)  # (R, V)
        active, crashed, is_cav = pick(state.active), pick(state.crashed), pick(state.is_cav)
        a, b = (slice(None), slice(None), None), (slice(None), None, slice(None))
        shares_lane = (
            (lf[a] == lf[b]) | (lf[a] == lt[b]) | (lt[a] == lf[b]) | (lt[a] == lt[b])
        )  # (R, V, V)
        dx = x[b] - x[a]  # (R, V, V) x_j - x_i
        ahead = np.where(shares_lane & (dx > 0.0) & active[b], dx, np.inf)
        leader = ahead.argmin(axis=2)  # (R, V)
        has_leader = np.isfinite(take_last(ahead, leader[..., None])[..., 0])

        def of_leader(values: np.ndarray) -> np.ndarray:  # (R, V) values of each leader
            return take_last(values, leader)

        hdv = active & ~is_cav & ~crashed
        guarded = hdv & has_leader & ~of_leader(is_cav)
        # Pairs that can still start a contact: both on the road, not both wrecked.
        pairs_active = active[a] & active[b] & self._not_self & ~(crashed[a] & crashed[b])
        moving = active & ~crashed & (lf != lt)
        screen = has_leader & ~(crashed & of_leader(crashed))
        for name, value in (
            ("leader", leader),
            ("has_leader", has_leader),
            ("guarded", guarded),
            ("pairs_active", pairs_active),
            ("moving", moving),
            ("screen", screen),
        ):
            if every:
                setattr(caches, name, value)
            else:
                getattr(caches, name)[rows] = value
        caches.leaders_dirty = np.zeros_like(caches.leaders_dirty)

    def _substep(self) -> np.ndarray:
        """Integrate one sub-step for all vehicles; return the (E, V, V) contact matrix.

        (``np.count_nonzero`` tests a bool array for any True at a third of the cost
        of ``.any()``: this runs ten times per decision step.)
        """
        state, caches = self.state, self.caches
        m, sim, dt = self.model, self.sim, self.dt_s
        x, v, length = state.x_m, state.speed_mps, sim.vehicle_length_m
        if np.count_nonzero(caches.leaders_dirty):
            self._refresh_leaders()
        leader = caches.leader
        leader_flat = leader + flat_offsets(leader.shape[:1], leader.shape[1], 1)  # (E, V)

        def at_leader(values: np.ndarray) -> np.ndarray:  # (E, V) values of each leader
            return np.ascontiguousarray(values).reshape(-1).take(leader_flat)

        # HDV longitudinal: IDM towards the nearer of the leader and the end of the
        # destination lane (a standing obstacle; a leader before it stops for it too).
        gap = np.where(caches.has_leader, at_leader(x) - x, np.inf)  # (E, V)
        to_end = caches.end_x_m - x
        end_closer = to_end < gap
        gap = np.where(end_closer, to_end, gap) - length
        lead_v = np.where(end_closer, 0.0, at_leader(v))
        acc = self._idm_fast(v, gap, lead_v)
        # A yielding follower brakes for the merger *and* for its own leader, whichever
        # asks more: the merger may be alongside the real leader, not in front of it.
        yielding = state.yield_to >= 0
        if np.count_nonzero(yielding):
            merger = np.where(yielding, state.yield_to, self._rows)
            acc_merge = self._idm_fast(v, take(x, merger) - x - length, take(v, merger))
            acc = np.where(yielding, np.minimum(acc, acc_merge), acc)
        # CAVs: constant acceleration towards the commanded target speed.
        acc = np.where(state.is_cav, state.cav_accel_mps2, np.maximum(acc, self._min_accel))
        v_new = np.minimum(np.maximum(v + acc * dt, caches.v_lo_mps), caches.v_hi_mps)
        x_new = x + (v + v_new) * caches.half_dt_active_s
        # A CAV cannot drive past the end of its lane: it stops with its front there.
        wall_x = caches.end_x_m - length
        at_wall = state.is_cav & (x_new > wall_x)
        if np.count_nonzero(at_wall):
            self.stats["cav_lane_end_stops"] += (at_wall & (v_new > 0.0)).sum(axis=1)
            x_new = np.where(at_wall, wall_x, x_new)
            v_new = np.where(at_wall, 0.0, v_new)

        # Last-resort guard: an HDV never runs into the HDV it follows.
        leader_x = at_leader(x_new)
        limit_x = leader_x - length - m.guard_gap_m
        guard = caches.guarded & (x_new > limit_x)
        if np.count_nonzero(guard):
            self.stats["guard_events"] += guard.sum(axis=1)
            x_new = np.where(guard, limit_x, x_new)
            v_new = np.where(guard, np.minimum(v_new, at_leader(v_new)), v_new)
            leader_x = at_leader(x_new)
        state.x_m, state.speed_mps = x_new, v_new

        # Lateral motion; the manoeuvre completes when the destination centre is reached.
        # Vehicles not changing lanes get lat = 0, y unchanged and heading 0.
        env_moving = caches.moving.any(axis=1)  # (E,)
        any_moving = np.count_nonzero(env_moving) > 0
        if any_moving:
            lat = np.where(caches.moving, state.lat_speed_mps, 0.0)
            y_goal = (state.lane_to + 0.5) * self.road.lane_width_m
            y_new = state.y_m + lat * dt
            done = caches.moving & ((y_goal - y_new) * np.sign(lat) <= 1e-9)
            state.y_m = np.where(done, y_goal, y_new)
            heading = np.arctan2(lat, v_new)  # v_new >= 0
            state.heading_rad = np.minimum(
                np.maximum(heading, -m.max_heading_rad), m.max_heading_rad
            )
            if np.count_nonzero(done):
                state.lane_from = np.where(done, state.lane_to, state.lane_from)
                state.lat_speed_mps = np.where(done, 0.0, state.lat_speed_mps)
                state.cooldown_s = np.where(done, m.lane_change_cooldown_s, state.cooldown_s)
                caches.leaders_dirty |= done.any(axis=1)
        elif caches.heading_nonzero:
            state.heading_rad = np.zeros_like(state.heading_rad)
        caches.heading_nonzero = any_moving
        state.cooldown_s = np.maximum(state.cooldown_s - dt, 0.0)  # LANE_CHANGE_DELAY counts down

        # Collisions: a cheap screen first, the exact box test only if it fires. Without
        # lateral motion every vehicle of an env is straight in one lane and cannot skip
        # over its leader within a sub-step, so only leader pairs can touch; otherwise
        # screen all the env's pairs by bounding boxes.
        maybe = (caches.screen & (leader_x - x_new < length)).any(axis=1)  # (E,)
        if any_moving:  # bounding boxes in the envs with lateral motion (R of them)
            rows = np.flatnonzero(env_moving)
            pick = (lambda a: a) if len(rows) == len(env_moving) else (lambda a: a[rows])  # noqa: E731
            heading, xs, ys = pick(state.heading_rad), pick(x_new), pick(state.y_m)  # (R, V)
            length_m, width_m = sim.vehicle_length_m, sim.vehicle_width_m
            cos_h, sin_h = np.abs(np.cos(heading)), np.abs(np.sin(heading))
            ext_x = 0.5 * (length_m * cos_h + width_m * sin_h)  # (R, V)
            ext_y = 0.5 * (length_m * sin_h + width_m * cos_h)
            near = (
                np.abs(xs[:, :, None] - xs[:, None, :]) < ext_x[:, :, None] + ext_x[:, None, :]
            ) & (
                np.abs(ys[:, :, None] - ys[:, None, :]) < ext_y[:, :, None] + ext_y[:, None, :]
            )  # (R, V, V)
            maybe[rows] = (near & pick(caches.pairs_active)).any(axis=(1, 2))
        if np.count_nonzero(maybe):
            contact = box_contacts(
                state.x_m,
                state.y_m,
                state.heading_rad,
                length,
                sim.vehicle_width_m,
                state.active,
            )
            contact &= caches.pairs_active & maybe[:, None, None]
            if np.count_nonzero(contact):
                hit = contact.any(axis=1) | contact.any(axis=2)  # (E, V)
                state.crashed |= hit
                state.speed_mps = np.where(hit, 0.0, state.speed_mps)
                state.lat_speed_mps = np.where(hit, 0.0, state.lat_speed_mps)
                self._refresh_speed_bounds()
                caches.leaders_dirty |= hit.any(axis=1)
        else:
            contact = self._no_contact

        # Arrivals.
        done_route = state.x_m > state.route_end_m
        if np.count_nonzero(done_route):
            state.active = state.active & ~done_route
            state.arrived |= done_route
            self._refresh_speed_bounds()
            state.route_end_m = np.where(done_route, np.inf, state.route_end_m)
            caches.leaders_dirty |= done_route.any(axis=1)
        return contact

    def _lane(self) -> np.ndarray:
        """(E, V) reported lane: the one the centre is in, within the manoeuvre's two."""
        state = self.state
        lo = np.minimum(state.lane_from, state.lane_to)
        hi = np.maximum(state.lane_from, state.lane_to)
        return np.minimum(np.maximum(np.floor(state.y_m / self.road.lane_width_m), lo), hi)

    def _make_state(
        self,
        e: int,
        lane: np.ndarray,
        accel_mps2: np.ndarray,
        collisions: np.ndarray,
        arrivals: np.ndarray,
    ) -> TrafficState:
        """Env ``e``'s TrafficState (copies of its rows); ``lane`` is :meth:`_lane`."""
        state, params = self.state, self.params
        n = state.x_m.shape[1]
        return TrafficState(
            time_s=float(state.time_s[e]),
            step=int(state.step_count[e]),
            vehicle_id=np.arange(n, dtype=np.int32),
            x_m=state.x_m[e].copy(),
            y_m=state.y_m[e].copy(),
            speed_mps=state.speed_mps[e].copy(),
            accel_mps2=np.asarray(accel_mps2, dtype=np.float64).copy(),
            heading_rad=state.heading_rad[e].copy(),
            lane=lane[e].astype(np.int16),
            segment=self.tables.segment_of(state.x_m[e]).astype(np.int16),
            length_m=np.full(n, self.sim.vehicle_length_m),
            width_m=np.full(n, self.sim.vehicle_width_m),
            is_cav=params.reported_cav[e].copy(),
            style=params.style[e].copy(),
            active=state.active[e].copy(),
            arrived=state.arrived[e].copy(),
            collisions=collisions.astype(np.int32).reshape(-1, 2),
            arrivals=arrivals.astype(np.int32),
        )

    def _make_batch_state(
        self, accel_mps2: np.ndarray, collisions: np.ndarray, arrivals: np.ndarray
    ) -> TrafficState:
        """Every env's TrafficState as one (E, V) batch (copies); rows (env, i, j) and (env, i)."""
        state, params = self.state, self.params
        shape = state.x_m.shape
        return TrafficState(
            time_s=state.time_s.copy(),
            step=state.step_count.copy(),
            vehicle_id=np.broadcast_to(np.arange(shape[1], dtype=np.int32), shape).copy(),
            x_m=state.x_m.copy(),
            y_m=state.y_m.copy(),
            speed_mps=state.speed_mps.copy(),
            accel_mps2=np.asarray(accel_mps2, dtype=np.float64).copy(),
            heading_rad=state.heading_rad.copy(),
            lane=self._lane().astype(np.int16),
            segment=self.tables.segment_of(state.x_m).astype(np.int16),
            length_m=np.full(shape, self.sim.vehicle_length_m),
            width_m=np.full(shape, self.sim.vehicle_width_m),
            is_cav=params.reported_cav.copy(),
            style=params.style.copy(),
            active=state.active.copy(),
            arrived=state.arrived.copy(),
            collisions=collisions,
            arrivals=arrivals,
        )
