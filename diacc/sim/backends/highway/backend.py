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
* **No HDV lane change into a crash**: MOBIL's incentive compares unclipped IDM
  accelerations, so with a car cutting in just ahead a lane behind a much slower
  car can "gain"; a change is made only if the driver's own IDM deceleration
  behind its new leader is within ``max_brake_mps2`` (like LC2013's secure gap to
  the new leader; vetoes counted in ``stats["unsafe_change_vetoes"]``). Of two
  drivers entering one lane side by side in the same instant only the front one
  goes, of two level ones (entered in the same sub-step) the one listed first.
* **Cooperative CAVs** (``SimConfig.cav_mode="cooperative"``, the paper's non-learning
  "cooperative" baseline; SUMO uses CACC with ``lcCooperative = 1``): CAVs
  ignore the commands and are driven by the same vectorised IDM / MOBIL /
  forced-merge code as HDVs, with a CACC-like parameter set
  (:class:`CooperativeCavParams`: its ``time_headway_s`` and ``min_gap_m``, the
  CAV vType's as SUMO's CACC is given them; the CAV accel/decel limits; MOBIL
  ``politeness`` that weighs the followers' gain as the own, i.e. fully cooperative
  lane changes). They are still reported as CAVs in the TrafficState.
* **Collisions** are oriented-rectangle overlaps between active vehicles at
  any sub-step. A pair is reported in the step its contact begins. Collided
  vehicles stop where they are and stay on the road as obstacles (as in
  highway-env) for the rest of the step; then the environment ends the episode
  or, with ``SimConfig.on_collision = "remove"``, they leave the road
  (inactive, never arrived) and the episode goes on.
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

import numpy as np

from diacc.sim.backends.base import BackendError, CavCommands
from diacc.sim.backends.highway.dynamics import refresh_road_facts, refresh_speed_bounds, substep
from diacc.sim.backends.highway.export import traffic_state
from diacc.sim.backends.highway.insertion import initial_records, insert_due
from diacc.sim.backends.highway.lanes import apply_cav_commands, decide_lane_changes
from diacc.sim.backends.highway.models import CooperativeCavParams, HighwayModel
from diacc.sim.backends.highway.road import LaneTables, build_road_network
from diacc.sim.backends.highway.simstate import HighwayCaches, HighwayParams, HighwayState
from diacc.sim.maps import Map
from diacc.sim.scenario import Scenario, draw_population
from diacc.sim.settings import SimConfig
from diacc.sim.state import TrafficState, take_last

__all__ = ["CooperativeCavParams", "HighwayBackend"]

_NO_EVENTS = np.zeros((0, 3), dtype=np.int32)


class HighwayBackend:
    """Vectorised highway traffic on a highway-env road (see module docstring).

    One object simulates ``n_envs`` environments of the same map and
    scenario, each its own block of (V,) rows in (E, V) arrays: every sub-step
    updates all vehicles of all envs at once, and nothing couples two envs.
    It is reset env by env (:meth:`reset`) and stepped together
    (:meth:`step`), with the same results per env as E separate backends
    (``tests/test_highway_batch.py``); E = 1 is one env.

    The arrays are three records (:mod:`.simstate`), created at the first
    reset: :attr:`state` (what a step changes), :attr:`params` (per-vehicle
    parameters fixed at reset) and :attr:`caches` (derived quantities kept
    between sub-steps). Copies of the three and of :attr:`stats` put a batch
    back exactly where it was (``tests/test_highway_simstate.py``).

    Work that the single-env simulator skips when nothing happened (leader
    search, lane-change decisions, the exact box test) is skipped only when
    it is a no-op for every env; where some envs need it, its results are
    kept for those envs alone (:func:`.dynamics.rows_where`), so skipping stays
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
        self.model = model or HighwayModel.of(sim.highway_merges)
        self.n_envs = n_envs
        self.network = build_road_network(road)
        self.tables = LaneTables.from_map(road)
        self.dt_s = sim.step_s / sim.substeps
        self._decide_every = max(1, int(round(self.model.decision_period_s / self.dt_s)))
        self._ready = np.zeros(n_envs, dtype=bool)  # (E,) env has been reset
        #: Per-env event counters, each (E,) int64.
        self.stats: dict[str, np.ndarray] = {
            key: np.zeros(n_envs, np.int64)
            for key in (
                "guard_events",
                "forced_merges",
                "mobil_changes",
                "unsafe_change_vetoes",
                "cav_lane_end_stops",
            )
        }

    # ------------------------------------------------------------------ API
    def reset(self, scenario: Scenario, seed: int, env: int = 0) -> TrafficState:
        """Start env ``env`` anew with ``draw_population(scenario, road, seed)``; its t = 0
        state, a batch of one.

        The other envs are untouched. Every env must be reset once before the
        first :meth:`step`; all envs carry the same number of vehicles.
        """
        if not 0 <= env < self.n_envs:
            raise BackendError(f"env {env} is not one of the backend's {self.n_envs}")
        pop = draw_population(scenario, self.road, seed)
        n = pop.n_vehicles
        if not self._ready.any():
            self._allocate(n)
        elif n != self.state.x_m.shape[1]:
            raise BackendError(f"env {env} has {n} vehicles, the batch {self.state.x_m.shape[1]}")
        params, state = initial_records(self, pop)
        self.params.set_rows(np.array([env]), params)
        self.state.set_rows(np.array([env]), state)
        for counts in self.stats.values():
            counts[env] = 0
        self._ready[env] = True
        only = np.arange(self.n_envs) == env  # (E,)
        self.caches.leaders_dirty[env] = True
        refresh_road_facts(self, only)
        refresh_speed_bounds(self)
        return traffic_state(self, env, np.zeros((1, n)), _NO_EVENTS, _NO_EVENTS[:, :2])

    def step(self, commands: CavCommands) -> TrafficState:
        """Advance every env one decision step (``sim.substeps`` integration sub-steps);
        ``commands`` arrays are (E, V), the state an (E, V) batch (:mod:`diacc.sim.state`)."""
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
        if self.sim.on_collision == "remove" and contacts.shape[0]:
            self._remove(contacts)
        arrivals = np.argwhere(new_arrivals).astype(np.int32).reshape(-1, 2)  # (A, 2) env, i
        return traffic_state(self, None, accel, contacts, arrivals)

    def close(self) -> None:
        """Nothing to release: the simulation is arrays in this process."""

    def _remove(self, contacts: np.ndarray) -> None:
        """Take the vehicles of ``contacts`` (K, 3) rows (env, i, j) off the road: inactive,
        not arrived, standing (``crashed``) where they collided (``on_collision = "remove"``)."""
        state = self.state
        hit = np.zeros(state.active.shape, bool)  # (E, V)
        hit[contacts[:, 0], contacts[:, 1]] = True
        hit[contacts[:, 0], contacts[:, 2]] = True
        state.active &= ~hit
        state.crashed |= hit
        state.speed_mps = np.where(hit, 0.0, state.speed_mps)
        state.lat_speed_mps = np.where(hit, 0.0, state.lat_speed_mps)
        yields_to_hit = (state.yield_to >= 0) & take_last(hit, np.maximum(state.yield_to, 0))
        state.yield_to = np.where(yields_to_hit, -1, state.yield_to)
        self.caches.leaders_dirty |= hit.any(axis=1)
        refresh_speed_bounds(self)

    def _step_vehicles(self, lane_cmd: np.ndarray, dv_cmd: np.ndarray) -> np.ndarray:
        """The sub-steps of a decision step for the vehicles of :attr:`state` (all of them,
        or the window :meth:`_step_window` put there); commands are (E, V).

        Returns the (E, V, V) contacts that began during the step.
        """
        state = self.state
        apply_cav_commands(self, lane_cmd, dv_cmd)
        new_contacts = np.zeros_like(state.contact)  # (E, V, V)
        demand = state.pending.any()
        for k in range(self.sim.substeps):
            if demand:
                insert_due(self, state.time_s + k * self.dt_s)
            if k % self._decide_every == 0:
                decide_lane_changes(self)
            contact = substep(self)
            if contact is not self.no_contact:  # else no contact begins
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
        settled = (
            (state.arrived & (state.heading_rad == 0.0) & (state.yield_to < 0))
            | (state.pending & (self.params.depart_s > step_end_s))
            | (state.crashed & ~state.active & ~state.pending)  # removed after a collision
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
    def _allocate(self, n: int) -> None:
        """The (E, V) records of the batch (every row is written by :meth:`reset`)
        and the constants that follow from the batch's shape."""
        n_envs = self.n_envs
        self.state = HighwayState.zeros(n_envs, n)
        self.params = HighwayParams.zeros(n_envs, n, self.sim.idm_delta)
        self.caches = HighwayCaches.zeros(n_envs, n)
        self._shape_constants: dict[int, tuple[np.ndarray, ...]] = {}
        self._set_shape_constants(n)
        self.sides = np.array([-1, 0, 1])
        self.min_accel_mps2 = -self.model.max_brake_mps2

    def _set_shape_constants(self, n: int) -> None:
        """The constant arrays of a step over ``n`` vehicles per env (all V, or a window)."""
        if n not in self._shape_constants:
            self._shape_constants[n] = (
                np.zeros((self.n_envs, n, n), dtype=bool),  # (E, n, n) no contact
                ~np.eye(n, dtype=bool),  # (n, n) j is not i
                np.broadcast_to(np.arange(n), (self.n_envs, n)),  # (E, n) own vehicle index
            )
        self.no_contact, self.not_self, self.own_index = self._shape_constants[n]
