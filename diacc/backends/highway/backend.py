"""The fast ``highway`` backend: highway-env geometry, vectorised IDM/MOBIL traffic.

Road geometry is a highway-env ``RoadNetwork`` (:mod:`.road`), but the
traffic itself lives in (V,) NumPy arrays and every sub-step updates all
vehicles at once (:mod:`.models`): no Python loop over vehicles in
``step``. This is what makes the backend 100x+ faster than stock multi-agent
``highway-v0`` (``diacc.bench.highway``).

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
* **CAVs** follow their commands exactly (see :mod:`diacc.backends.base`).
  A commanded change is made only if :meth:`Map.lane_change_allowed` says
  so (the rule PSAR applies too). A CAV is never moved by the simulator: in
  a lane that ends it stops with its front at the end (counted in
  ``stats["cav_lane_end_stops"]`` when it arrives there moving) and may
  change lanes later.
* **HDV lane changes respect CAVs**: MOBIL and the forced merge accept a gap
  in front of a CAV only if the CAV, holding its commanded speed for the
  step and then braking at ``cav.safe_decel_mps2``, stays ``cav.min_gap_m`` behind
  (:func:`diacc.kinematics.safe_gap_m`, the margin PSAR uses); IDM's view
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
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from diacc.backends.base import BackendError, CavCommands
from diacc.backends.highway.models import (
    HighwayModel,
    IdmParams,
    box_contacts,
    idm_accel,
)
from diacc.backends.highway.road import LaneTables, build_road_network
from diacc.config import STYLE_PRESETS, SimConfig
from diacc.kinematics import lane_change_reach_m, safe_gap_m
from diacc.maps import Map
from diacc.scenario import Scenario, draw_population
from diacc.state import TrafficState

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


class HighwayBackend:
    """Vectorised highway traffic on a highway-env road (see module docstring)."""

    name = "highway"
    #: diacc's own NumPy dynamics, versioned with diacc (results record "").
    version = ""
    #: NumPy steps fast in one process; worker processes would only add pickling.
    vector_mode = "sync"

    def __init__(
        self,
        road: Map,
        sim: SimConfig,
        model: HighwayModel | None = None,
        cooperative: CooperativeCavParams | None = None,
    ) -> None:
        self.cav_mode = sim.cav_mode
        self.cooperative = cooperative or CooperativeCavParams()
        self.road = road
        self.sim = sim
        self.model = model or HighwayModel()
        self.network = build_road_network(road)
        self.tables = LaneTables.from_map(road)
        self.dt_s = sim.step_s / sim.substeps
        self._decide_every = max(1, int(round(self.model.decision_period_s / self.dt_s)))
        self._state: TrafficState | None = None
        self.stats: dict[str, int] = {}

    # ------------------------------------------------------------------ API
    def reset(self, scenario: Scenario, seed: int) -> TrafficState:
        """Insert ``draw_population(scenario, road, seed)`` and return the t = 0 state."""
        pop = draw_population(scenario, self.road, seed)
        n = pop.n_vehicles
        styles = STYLE_PRESETS[self.sim.style_preset]
        cav = self.sim.cav
        coop = self.cav_mode == "cooperative"
        headway_s = self.cooperative.time_headway_s if coop else cav.time_headway_s
        min_gap_m = self.cooperative.min_gap_m if coop else cav.min_gap_m
        hdv_style = np.where(pop.is_cav, 0, pop.style).astype(np.intp)

        def per_vehicle(attr: str, cav_value: float) -> np.ndarray:
            table = np.array([getattr(s, attr) for s in styles])
            return np.where(pop.is_cav, cav_value, table[hdv_style])

        self.idm = IdmParams(
            headway_s=per_vehicle("time_headway_s", headway_s),
            min_gap_m=per_vehicle("min_gap_m", min_gap_m),
            accel_mps2=per_vehicle("accel_mps2", cav.accel_mps2),
            decel_mps2=per_vehicle("decel_mps2", cav.decel_mps2),
            delta=self.sim.idm_delta,
        )
        self.politeness = per_vehicle("politeness", self.cooperative.politeness if coop else 0.0)
        self.gain_threshold_mps2 = per_vehicle(
            "lc_gain_threshold_mps2", self.cooperative.lc_gain_threshold_mps2 if coop else 0.0
        )
        # LC2013's lcStrategic < 0 (the authors' cautious drivers): no lane change
        # because a lane ends, so such a driver stops at the end of its lane.
        self.strategic = per_vehicle("lc_strategic", 0.0) >= 0.0

        # is_cav: vehicles driven by commands; cooperative CAVs drive like HDVs.
        self.is_cav = np.zeros(n, dtype=bool) if coop else pop.is_cav.copy()
        self._reported_cav = pop.is_cav.copy()  # TrafficState.is_cav
        self.style = pop.style.astype(np.int8)
        self.x_m = pop.x_m.astype(np.float64).copy()
        self.lane_from = pop.lane.astype(np.intp)
        self.lane_to = self.lane_from.copy()
        self.y_m = self.road.lane_center_y_m(self.lane_from).astype(np.float64)
        self.speed_mps = pop.speed_mps.astype(np.float64).copy()
        self.lat_speed_mps = np.zeros(n)
        self.heading_rad = np.zeros(n)
        self.cooldown_s = np.zeros(n)
        self.active = np.ones(n, dtype=bool)
        self.arrived = np.zeros(n, dtype=bool)
        self.crashed = np.zeros(n, dtype=bool)
        self.yield_to = np.full(n, -1, dtype=np.intp)
        self._contact = np.zeros((n, n), dtype=bool)
        self._rows = np.arange(n)
        self._not_self = ~np.eye(n, dtype=bool)
        self._inv_2_sqrt_ab = 0.5 / np.sqrt(self.idm.accel_mps2 * self.idm.decel_mps2)
        self._zeros = np.zeros(n)
        self._zeros3 = np.zeros((3, n))
        self._sides = np.array([-1, 0, 1])
        self._min_accel = -self.model.max_brake_mps2
        self._route_end_m = np.full(n, self.road.length_m)
        self._no_contact = np.zeros((n, n), dtype=bool)
        self._heading_nonzero = False
        self._leaders_dirty = True
        self._cav_target_mps = self.speed_mps.copy()
        self._cav_accel_mps2 = np.zeros(n)
        self._update_reach()
        self._refresh_road_facts()
        self._refresh_speed_bounds()
        self.time_s = 0.0
        self.step_count = 0
        self.stats = {
            "guard_events": 0,
            "forced_merges": 0,
            "mobil_changes": 0,
            "cav_lane_end_stops": 0,
        }
        self._state = self._make_state(np.zeros(n), _EMPTY_PAIRS, np.zeros(0, np.int32))
        return self._state

    def step(self, commands: CavCommands) -> TrafficState:
        """Advance one decision step (``sim.substeps`` integration sub-steps)."""
        if self._state is None:
            raise BackendError("step() called before reset()")
        n = self.is_cav.shape[0]
        lane_cmd = np.asarray(commands.lane_change)
        dv_cmd = np.asarray(commands.speed_change_mps, dtype=np.float64)
        if lane_cmd.shape != (n,) or dv_cmd.shape != (n,):
            raise BackendError(
                f"commands must have shape ({n},), got {lane_cmd.shape} and {dv_cmd.shape}"
            )
        speed_start = self.speed_mps.copy()
        self._apply_cav_commands(lane_cmd.astype(np.intp), dv_cmd)
        arrived_before = self.arrived.copy()
        new_contacts = np.zeros((n, n), dtype=bool)
        for k in range(self.sim.substeps):
            if k % self._decide_every == 0:
                self._decide_lane_changes()
            contact = self._substep()
            new_contacts |= contact & ~self._contact
            self._contact = contact
        self.time_s += self.sim.step_s
        self.step_count += 1
        pairs = np.argwhere(new_contacts).astype(np.int32).reshape(-1, 2)
        arrivals = np.flatnonzero(self.arrived & ~arrived_before).astype(np.int32)
        accel = (self.speed_mps - speed_start) / self.sim.step_s
        self._state = self._make_state(accel, pairs, arrivals)
        return self._state

    def close(self) -> None:
        """Nothing to release: the simulation is arrays in this process."""

    # ------------------------------------------------------------ internals
    def _segment(self) -> np.ndarray:
        return self.tables.segment_of(self.x_m)

    def _apply_cav_commands(self, lane_cmd: np.ndarray, dv_cmd: np.ndarray) -> None:
        """Fix each CAV's acceleration for the step and start commanded lane changes."""
        seg = self._segment()
        limit = self.tables.speed_limit_mps[seg]
        cav = self.is_cav & self.active & ~self.crashed
        target = np.clip(self.speed_mps + dv_cmd, 0.0, limit)
        accel = np.clip(
            (target - self.speed_mps) / self.sim.step_s,
            -self.sim.cav.decel_mps2,
            self.sim.cav.accel_mps2,
        )
        self._cav_target_mps = np.where(cav, target, self.speed_mps)
        self._cav_accel_mps2 = np.where(cav, accel, 0.0)
        self._refresh_speed_bounds()

        offset = np.clip(lane_cmd, -1, 1)
        reach_m = lane_change_reach_m(self.speed_mps, self.sim.step_s, self.sim.vehicle_length_m)
        ok = (
            cav
            & (self.lane_from == self.lane_to)
            & self.road.lane_change_allowed(seg, self.lane_from, offset, self.x_m, reach_m)
        )
        dest_c = np.clip(self.lane_from + offset, 0, self.road.max_lanes - 1)
        self._start_changes(ok, dest_c, self.sim.step_s)

    def _start_changes(self, start: np.ndarray, dest: np.ndarray, duration_s: float) -> None:
        width = self.road.lane_width_m
        direction = np.sign(dest - self.lane_from)
        self.lane_to = np.where(start, dest, self.lane_to)
        self.lat_speed_mps = np.where(start, direction * width / duration_s, self.lat_speed_mps)
        if start.any():
            self._leaders_dirty = True
            self._refresh_road_facts()
            self._moving = self.active & ~self.crashed & (self.lane_from != self.lane_to)

    def _occupancy(self) -> np.ndarray:
        """(V, L + 2) bool: lanes each active vehicle occupies, padded by one lane per side."""
        n, n_lanes = self.is_cav.shape[0], self.road.max_lanes
        occ = np.zeros((n, n_lanes + 2), dtype=bool)
        occ[self._rows, self.lane_from + 1] = True
        occ[self._rows, self.lane_to + 1] = True
        occ &= self.active[:, None]
        return occ

    def _decide_lane_changes(self) -> None:
        """MOBIL for HDVs, forced merges for vehicles in ending lanes, yielding followers.

        All vehicles and all three lanes (right, own, left) are evaluated at
        once: one (3, V, V) neighbour search and a single IDM call over every
        acceleration MOBIL needs, stacked as (4, 3, V).
        """
        m, sim, tab = self.model, self.sim, self.tables
        x, v, length = self.x_m, self.speed_mps, sim.vehicle_length_m
        n, n_lanes = x.shape[0], self.road.max_lanes
        self._refresh_road_facts()
        seg = self._segment()
        desired = self._desired_mps

        idle = self.active & ~self.crashed & (self.lane_from == self.lane_to)
        lane = self.lane_from
        dist_end = tab.end_m[seg, lane] - x
        merge_dir = tab.merge_dir[seg, lane].astype(np.intp)
        # Only HDVs are forced to merge (a CAV that stays in an ending lane stops at its
        # end), and only drivers with a strategic lane-change term (lcStrategic >= 0).
        near_end = idle & (merge_dir != 0) & (dist_end < m.merge_zone_m)
        forced = near_end & self.strategic & ~self.is_cav
        discretionary = (
            idle
            & ~self.is_cav
            & ~near_end
            & (self.cooldown_s <= 0.0)
            & (v >= m.min_lane_change_speed_mps)
        )
        if not (forced.any() or discretionary.any()):
            if (self.yield_to >= 0).any():
                self.yield_to[:] = -1
                self._leaders_dirty = True
            return

        # Neighbours in the right / own / left lane: (3, V) each.
        lanes3 = lane[None, :] + self._sides[:, None]  # (3, V)
        lanes3_c = np.clip(lanes3, 0, n_lanes - 1)
        occ = self._occupancy()  # (V, L+2)
        in_lane = occ[:, lanes3 + 1].transpose(1, 2, 0) & self._peers()  # (3, V, V)
        dx = x[None, :] - x[:, None]  # (V, V) x_j - x_i
        ahead = np.where(in_lane & (dx >= 0.0), dx, np.inf)  # (3, V, V)
        behind = np.where(in_lane & (dx < 0.0), -dx, np.inf)
        lead = ahead.argmin(axis=2)  # (3, V)
        foll = behind.argmin(axis=2)
        lead_gap = np.take_along_axis(ahead, lead[..., None], 2)[..., 0] - length
        foll_gap = np.take_along_axis(behind, foll[..., None], 2)[..., 0] - length
        has_foll = np.isfinite(foll_gap)

        # Every IDM acceleration MOBIL needs, in one call: (4, 3, V) =
        # [ego behind lane leader, ego before lane end, follower behind ego,
        #  follower behind lane leader].
        me = np.broadcast_to(self._rows, (3, n))
        ego = np.stack([me, me, foll, foll])  # (4, 3, V)
        end_gap = tab.end_m[seg, lanes3_c] - x - 0.5 * length
        gaps = np.stack([lead_gap, end_gap, foll_gap, foll_gap + lead_gap + length])
        lead_v = np.stack([v[lead], self._zeros3, np.broadcast_to(v, (3, n)), v[lead]])
        acc = idm_accel(v[ego], desired[ego], self.idm.take(ego), gaps, lead_v)
        self_acc = np.minimum(acc[0], acc[1])  # (3, V)
        foll_with_me = np.where(has_foll, acc[2], 0.0)
        foll_without = np.where(has_foll, acc[3], 0.0)

        side = [0, 2]  # rows of the right and left lanes
        dest = lanes3[side]  # (2, V)
        dest_c = lanes3_c[side]
        valid = (dest >= 0) & (dest < n_lanes) & tab.exists[seg, dest_c]
        gaps_ok = (lead_gap[side] >= m.min_accept_gap_m) & (foll_gap[side] >= m.min_accept_gap_m)
        # A CAV follower holds its commanded speed for the rest of the step and only
        # then brakes (at most at its decel limit): the gap must cover that, not IDM.
        cav_foll = self.is_cav[foll[side]] & has_foll[side]  # (2, V)
        cav_gap_m = sim.cav.min_gap_m + safe_gap_m(
            self._cav_target_mps[foll[side]], v[None, :], sim.step_s, sim.cav.safe_decel_mps2
        )
        gaps_ok &= ~cav_foll | (foll_gap[side] >= cav_gap_m)
        nf_after = foll_with_me[side]
        gain = (
            self_acc[side]
            - self_acc[1]
            + self.politeness * (nf_after - foll_without[side] + foll_without[1] - foll_with_me[1])
        )
        mobil_ok = (
            discretionary
            & valid
            & (tab.end_m[seg, dest_c] - x > m.merge_zone_m + m.merge_lookahead_m)
            & gaps_ok
            & (nf_after >= -m.mobil_max_imposed_brake_mps2)
            & (gain >= self.gain_threshold_mps2)
        )
        urgency = np.clip(1.0 - dist_end / m.merge_zone_m, 0.0, 1.0)
        accept_brake = m.mobil_max_imposed_brake_mps2 + urgency * (
            m.forced_max_imposed_brake_mps2 - m.mobil_max_imposed_brake_mps2
        )
        is_merge = forced & valid & (merge_dir == self._sides[side, None])  # (2, V)
        forced_ok = (
            is_merge & gaps_ok & (nf_after >= -accept_brake) & (self_acc[side] >= -accept_brake)
        )
        score = np.where(forced_ok, np.inf, np.where(mobil_ok, gain, -np.inf))  # (2, V)
        pick = score.argmax(axis=0)  # (V,)
        start = score[pick, self._rows] > -np.inf
        target = dest_c[pick, self._rows]

        # Two vehicles entering the same lane side by side in the same instant
        # would not see each other: keep the front one.
        priority = x
        rear_gap_need = self.idm.min_gap_m + v * self.idm.headway_s  # (V,)
        clash = (
            start[:, None]
            & start[None, :]
            & (target[:, None] == target[None, :])
            & self._not_self
            & (np.abs(dx) - length < np.maximum(rear_gap_need[:, None], rear_gap_need[None, :]))
            & (priority[None, :] > priority[:, None])
        )
        start &= ~clash.any(axis=1)

        self.stats["forced_merges"] += int((start & forced).sum())
        self.stats["mobil_changes"] += int((start & ~forced).sum())
        self._start_changes(start, target, m.hdv_lane_change_s)

        # Yielding: the nearest follower in the merge lane treats a waiting merger as leader.
        merge_row = np.where(merge_dir > 0, 2, 0)
        nf = foll[merge_row, self._rows]
        nf_gap = foll_gap[merge_row, self._rows]
        nf_acc = foll_with_me[merge_row, self._rows]
        polite = (self.politeness[nf] > 0.0) | (v < m.yield_speed_mps)
        waiting = (
            forced
            & ~start
            & (dist_end < m.yield_zone_m)
            & (nf_gap > 0.0)
            & np.isfinite(nf_gap)
            & ~self.is_cav[nf]
            & polite
            & (nf_acc >= -self.idm.decel_mps2[nf])
        )
        yield_to = np.full_like(self.yield_to, -1)
        mergers = np.flatnonzero(waiting)
        if mergers.size:
            order = mergers[np.argsort(-x[mergers], kind="stable")]  # nearest merger written last
            yield_to[nf[order]] = order
        if not np.array_equal(yield_to, self.yield_to):
            self.yield_to = yield_to
            self._leaders_dirty = True

    def _peers(self) -> np.ndarray:
        """(V, V) bool: j is another vehicle on the road."""
        return self._not_self & self.active[None, :]

    def _refresh_road_facts(self) -> None:
        """Per-vehicle desired speed and end of the destination lane.

        Refreshed at every decision and lane-change start rather than every
        sub-step: both only change at segment boundaries, so a new speed
        limit takes effect at the next decision (<= ``decision_period_s``).
        """
        seg = self._segment()
        self._desired_mps = self.tables.speed_limit_mps[seg]
        # Lane end as a centre position: the obstacle's rear is at the end itself.
        self._end_x_m = self.tables.end_m[seg, self.lane_to] + 0.5 * self.sim.vehicle_length_m
        self._inv_desired = 1.0 / np.maximum(self._desired_mps, 1e-3)

    def _refresh_speed_bounds(self) -> None:
        """Per-vehicle speed window of a sub-step: [0, inf) for HDVs, up to / down to
        the commanded target for CAVs, frozen for wrecked and arrived vehicles."""
        driving = self.active & ~self.crashed
        up = self._cav_accel_mps2 >= 0.0
        lo = np.where(self.is_cav & ~up, self._cav_target_mps, 0.0)
        hi = np.where(self.is_cav & up, self._cav_target_mps, np.inf)
        self._v_lo = np.where(driving, lo, self.speed_mps)
        self._v_hi = np.where(driving, hi, self.speed_mps)
        self._half_dt_active = np.where(self.active, 0.5 * self.dt_s, 0.0)

    def _idm_fast(self, v: np.ndarray, gap_m: np.ndarray, lead_v: np.ndarray) -> np.ndarray:
        """:func:`idm_accel` with per-vehicle constants folded in (the sub-step hot path)."""
        p = self.idm
        free = np.power(v * self._inv_desired, p.delta)
        dynamic = v * (p.headway_s + (v - lead_v) * self._inv_2_sqrt_ab)
        s_star = p.min_gap_m + np.maximum(dynamic, 0.0)
        ratio = s_star / np.maximum(gap_m, 1e-2)
        return p.accel_mps2 * (1.0 - free - ratio * ratio)

    def _refresh_leaders(self) -> None:
        """Leader of every vehicle: nearest active vehicle ahead sharing a lane.

        (A merger a vehicle yields to is a second leader, handled in the sub-step.)

        Leaders only change when a lane change starts or ends, a vehicle
        arrives or crashes, or yielding changes (vehicles in a shared lane
        cannot pass each other without a collision), so the (V, V) search runs
        on those events only and sub-steps reuse the result.
        """
        x, lf, lt = self.x_m, self.lane_from, self.lane_to
        shares_lane = (
            (lf[:, None] == lf[None, :])
            | (lf[:, None] == lt[None, :])
            | (lt[:, None] == lf[None, :])
            | (lt[:, None] == lt[None, :])
        )  # (V, V)
        dx = x[None, :] - x[:, None]  # (V, V)
        ahead = np.where(shares_lane & (dx > 0.0) & self.active[None, :], dx, np.inf)
        self._leader = ahead.argmin(axis=1)
        self._has_leader = np.isfinite(ahead[self._rows, self._leader])
        hdv = self.active & ~self.is_cav & ~self.crashed
        self._guarded = hdv & self._has_leader & ~self.is_cav[self._leader]
        # Pairs that can still start a contact: both on the road, not both wrecked.
        self._pairs_active = (
            self.active[:, None]
            & self.active[None, :]
            & self._not_self
            & ~(self.crashed[:, None] & self.crashed[None, :])
        )
        self._moving = self.active & ~self.crashed & (lf != lt)
        self._screen = self._has_leader & ~(self.crashed & self.crashed[self._leader])
        self._leaders_dirty = False

    def _update_reach(self) -> None:
        """(V, V) centre distances below which two boxes *may* touch (from headings)."""
        length, width = self.sim.vehicle_length_m, self.sim.vehicle_width_m
        cos_h, sin_h = np.abs(np.cos(self.heading_rad)), np.abs(np.sin(self.heading_rad))
        ext_x = 0.5 * (length * cos_h + width * sin_h)  # (V,)
        ext_y = 0.5 * (length * sin_h + width * cos_h)
        self._reach_x_m = ext_x[:, None] + ext_x[None, :]  # (V, V)
        self._reach_y_m = ext_y[:, None] + ext_y[None, :]

    def _substep(self) -> np.ndarray:
        """Integrate one sub-step for all vehicles; return the (V, V) contact matrix."""
        m, sim, dt = self.model, self.sim, self.dt_s
        x, v, length = self.x_m, self.speed_mps, sim.vehicle_length_m
        if self._leaders_dirty:
            self._refresh_leaders()
        leader = self._leader
        n = x.shape[0]

        # HDV longitudinal: IDM towards the nearer of the leader and the end of the
        # destination lane (a standing obstacle; a leader before it stops for it too).
        gap = np.where(self._has_leader, x[leader] - x, np.inf)
        end_closer = self._end_x_m - x < gap
        gap = np.where(end_closer, self._end_x_m - x, gap) - length
        lead_v = np.where(end_closer, 0.0, v[leader])
        acc = self._idm_fast(v, gap, lead_v)
        # A yielding follower brakes for the merger *and* for its own leader, whichever
        # asks more: the merger may be alongside the real leader, not in front of it.
        yielding = self.yield_to >= 0
        if yielding.any():
            merger = np.where(yielding, self.yield_to, self._rows)
            acc_merge = self._idm_fast(v, x[merger] - x - length, v[merger])
            acc = np.where(yielding, np.minimum(acc, acc_merge), acc)
        # CAVs: constant acceleration towards the commanded target speed.
        acc = np.where(self.is_cav, self._cav_accel_mps2, np.maximum(acc, self._min_accel))
        v_new = np.minimum(np.maximum(v + acc * dt, self._v_lo), self._v_hi)
        x_new = x + (v + v_new) * self._half_dt_active
        # A CAV cannot drive past the end of its lane: it stops with its front there.
        wall_x = self._end_x_m - length
        at_wall = self.is_cav & (x_new > wall_x)
        if at_wall.any():
            self.stats["cav_lane_end_stops"] += int((at_wall & (v_new > 0.0)).sum())
            x_new = np.where(at_wall, wall_x, x_new)
            v_new = np.where(at_wall, 0.0, v_new)

        # Last-resort guard: an HDV never runs into the HDV it follows.
        leader_x = x_new[leader]
        limit_x = leader_x - length - m.guard_gap_m
        guard = self._guarded & (x_new > limit_x)
        if guard.any():
            self.stats["guard_events"] += int(guard.sum())
            x_new = np.where(guard, limit_x, x_new)
            v_new = np.where(guard, np.minimum(v_new, v_new[leader]), v_new)
            leader_x = x_new[leader]
        self.x_m, self.speed_mps = x_new, v_new

        # Lateral motion; the manoeuvre completes when the destination centre is reached.
        any_moving = self._moving.any()
        if any_moving:
            lat = np.where(self._moving, self.lat_speed_mps, 0.0)
            y_goal = (self.lane_to + 0.5) * self.road.lane_width_m
            y_new = self.y_m + lat * dt
            done = self._moving & ((y_goal - y_new) * np.sign(lat) <= 1e-9)
            self.y_m = np.where(done, y_goal, y_new)
            heading = np.arctan2(lat, v_new)  # v_new >= 0
            self.heading_rad = np.minimum(
                np.maximum(heading, -m.max_heading_rad), m.max_heading_rad
            )
            self._update_reach()
            if done.any():
                self.lane_from = np.where(done, self.lane_to, self.lane_from)
                self.lat_speed_mps = np.where(done, 0.0, self.lat_speed_mps)
                self.cooldown_s = np.where(done, m.lane_change_cooldown_s, self.cooldown_s)
                self._leaders_dirty = True
        elif self._heading_nonzero:
            self.heading_rad = np.zeros(n)
            self._update_reach()
        self._heading_nonzero = any_moving

        # Collisions: a cheap screen first, the exact box test only if it fires. Without
        # lateral motion every vehicle is straight in one lane and cannot skip over its
        # leader within a sub-step, so only leader pairs can touch; otherwise screen all
        # pairs by bounding boxes.
        if any_moving:
            near = (np.abs(x_new[:, None] - x_new[None, :]) < self._reach_x_m) & (
                np.abs(self.y_m[:, None] - self.y_m[None, :]) < self._reach_y_m
            )
            maybe = (near & self._pairs_active).any()
        else:
            maybe = (self._screen & (leader_x - x_new < length)).any()
        if maybe:
            contact = box_contacts(
                self.x_m, self.y_m, self.heading_rad, length, sim.vehicle_width_m, self.active
            )
            contact &= self._pairs_active
            if contact.any():
                hit = contact.any(axis=0) | contact.any(axis=1)
                self.crashed |= hit
                self.speed_mps = np.where(hit, 0.0, self.speed_mps)
                self.lat_speed_mps = np.where(hit, 0.0, self.lat_speed_mps)
                self._refresh_speed_bounds()
                self._leaders_dirty = True
        else:
            contact = self._no_contact

        # Arrivals.
        done_route = self.x_m > self._route_end_m
        if done_route.any():
            self.active = self.active & ~done_route
            self.arrived |= done_route
            self._refresh_speed_bounds()
            self._route_end_m = np.where(done_route, np.inf, self._route_end_m)
            self._leaders_dirty = True
        return contact

    def _make_state(
        self, accel_mps2: np.ndarray, collisions: np.ndarray, arrivals: np.ndarray
    ) -> TrafficState:
        n = self.is_cav.shape[0]
        width = self.road.lane_width_m
        lo = np.minimum(self.lane_from, self.lane_to)
        hi = np.maximum(self.lane_from, self.lane_to)
        lane = np.clip(np.floor(self.y_m / width), lo, hi)
        return TrafficState(
            time_s=float(self.time_s),
            step=int(self.step_count),
            vehicle_id=np.arange(n, dtype=np.int32),
            x_m=self.x_m.copy(),
            y_m=self.y_m.copy(),
            speed_mps=self.speed_mps.copy(),
            accel_mps2=np.asarray(accel_mps2, dtype=np.float64).copy(),
            heading_rad=self.heading_rad.copy(),
            lane=lane.astype(np.int16),
            segment=self._segment().astype(np.int16),
            length_m=np.full(n, self.sim.vehicle_length_m),
            width_m=np.full(n, self.sim.vehicle_width_m),
            is_cav=self._reported_cav.copy(),
            style=self.style.copy(),
            active=self.active.copy(),
            arrived=self.arrived.copy(),
            collisions=collisions.astype(np.int32).reshape(-1, 2),
            arrivals=arrivals.astype(np.int32),
        )
