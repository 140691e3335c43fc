"""The highway backend's simulator state as typed (E, V) arrays, one row per env.

:class:`~diacc.sim.backends.highway.backend.HighwayBackend` keeps everything it
knows about the vehicles of a batch in three records, split by who writes
them and when:

* :class:`HighwayState`: what a step changes (positions, speeds, lanes,
  flags, timers, clocks). Together with the parameters it *is* the traffic.
* :class:`HighwayParams`: per-vehicle parameters drawn or derived once at
  reset (driver model, style, departure time) and never changed by a step.
* :class:`HighwayCaches`: quantities derived from the two above and kept
  between sub-steps only because recomputing them every sub-step is slow
  (leaders, lane ends, speed windows). Some are refreshed on events only,
  so they belong to the state of a running batch, too.

All three are :class:`~.rows.EnvRows`, batched records
(:class:`~diacc.records.Batched`): :meth:`~.rows.EnvRows.copy` (a deep copy, so a
batch can be checkpointed and restored exactly), ``env(e)`` (one env as an E = 1
record), ``set_rows`` (write envs' rows of every field, which is how ``reset``
starts an env: a field cannot be forgotten, since the record's constructor needs
them all) and :meth:`~.rows.EnvRows.window` /
:meth:`~.rows.EnvRows.put_window` (the vehicles the backend steps). Every
field declares its axes (``per_vehicle()``: (E, V), ``per_env()``: (E,),
``per_pair()``: (E, V, V), ``shared()``: one value for the batch,
``nested()``: a record such as :class:`~.models.IdmParams`), which is what a
window cuts by (see :mod:`.rows`); E is the batch size, V the vehicles per
env. The comments give the dtype and meaning.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from diacc.sim.backends.highway.models import CooperativeCavParams, HighwayModel, IdmParams
from diacc.sim.backends.highway.road import LaneTables
from diacc.sim.backends.highway.rows import (
    EnvRows,
    nested,
    per_env,
    per_pair,
    per_vehicle,
    shared,
)
from diacc.sim.maps import Map
from diacc.sim.settings import SimConfig


@dataclass(slots=True)
class HighwayState(EnvRows):
    """Dynamic vehicle state of a batch: everything a step changes.

    Pending vehicles (``demand`` scenarios) wait at their population slot,
    inactive; arrived ones are inactive and frozen where they left.
    """

    x_m: np.ndarray = per_vehicle()  # float64 centre position along the road
    y_m: np.ndarray = per_vehicle()  # float64 centre position across the road (0: right edge)
    speed_mps: np.ndarray = per_vehicle()  # float64 longitudinal speed, >= 0
    lat_speed_mps: np.ndarray = per_vehicle()  # float64 of the current lane change (0: none)
    heading_rad: np.ndarray = per_vehicle()  # float64 atan2(v_lat, v_long), clipped, last sub-step
    # Set to HighwayModel.lane_change_cooldown_s when a lane change completes; no code
    # counts it down at present, so it only marks "has completed a lane change".
    cooldown_s: np.ndarray = per_vehicle()  # float64
    lane_from: np.ndarray = per_vehicle()  # intp lane a manoeuvre starts in (= lane_to when idle)
    lane_to: np.ndarray = per_vehicle()  # intp destination lane of the manoeuvre
    active: np.ndarray = per_vehicle()  # bool on the road (entered, neither arrived nor pending)
    arrived: np.ndarray = per_vehicle()  # bool passed the end of the map
    crashed: np.ndarray = per_vehicle()  # bool collided; stands still as an obstacle
    pending: np.ndarray = per_vehicle()  # bool waiting to depart (demand scenarios)
    # Driven by commands this step; CAVs without a command (NaN), just-entered CAVs
    # and all CAVs in cooperative mode drive like HDVs and are False here.
    is_cav: np.ndarray = per_vehicle()  # bool
    yield_to: np.ndarray = per_vehicle()  # intp merger this vehicle yields to (-1: none)
    route_end_m: np.ndarray = per_vehicle()  # float64 x where it arrives (inf once arrived)
    cav_target_mps: np.ndarray = per_vehicle()  # float64 commanded speed (own speed if none)
    cav_accel_mps2: np.ndarray = per_vehicle()  # float64 constant CAV acceleration of the step
    contact: np.ndarray = per_pair()  # bool box contacts of the last sub-step
    time_s: np.ndarray = per_env()  # float64 simulated time
    step_count: np.ndarray = per_env()  # int64 decision steps since reset

    @classmethod
    def zeros(cls, n_envs: int, n_vehicles: int) -> HighwayState:
        """A batch record before any reset (a reset writes every row of its env)."""
        shape = (n_envs, n_vehicles)
        f64, flag, lane = np.zeros(shape), np.zeros(shape, bool), np.zeros(shape, np.intp)
        return cls(
            x_m=f64.copy(),
            y_m=f64.copy(),
            speed_mps=f64.copy(),
            lat_speed_mps=f64.copy(),
            heading_rad=f64.copy(),
            cooldown_s=f64.copy(),
            lane_from=lane.copy(),
            lane_to=lane.copy(),
            active=flag.copy(),
            arrived=flag.copy(),
            crashed=flag.copy(),
            pending=flag.copy(),
            is_cav=flag.copy(),
            yield_to=np.full(shape, -1, np.intp),
            route_end_m=f64.copy(),
            cav_target_mps=f64.copy(),
            cav_accel_mps2=f64.copy(),
            contact=np.zeros((n_envs, n_vehicles, n_vehicles), bool),
            time_s=np.zeros(n_envs),
            step_count=np.zeros(n_envs, np.int64),
        )


@dataclass(slots=True)
class HighwayParams(EnvRows):
    """Per-vehicle parameters of a batch, fixed at reset (a step never writes them).

    CAV rows hold the CAV vType's values (or the cooperative baseline's), so
    the vectorised IDM/MOBIL code treats every vehicle alike.
    """

    idm: IdmParams = nested()  # (E, V) float64 each: time headway, minimum gap, accel, decel
    inv_2_sqrt_ab_s2_per_m: np.ndarray = per_vehicle()  # float64 1 / (2 sqrt(a b)) of the IDM
    politeness: np.ndarray = per_vehicle()  # float64 MOBIL politeness factor
    gain_threshold_mps2: np.ndarray = per_vehicle()  # float64 MOBIL acceleration gain threshold
    strategic: np.ndarray = per_vehicle()  # bool changes lanes for a lane end (lcStrategic >= 0)
    zipper: np.ndarray = per_vehicle()  # bool lets a merger in when following it (zipper preset)
    merge_zone_m: np.ndarray = per_vehicle()  # float64 forced merging starts this far before an end
    reported_cav: np.ndarray = per_vehicle()  # bool a CAV in TrafficState.is_cav (whoever drives)
    style: np.ndarray = per_vehicle()  # int8 driver style code (TrafficState.style)
    depart_s: np.ndarray = per_vehicle()  # float64 departure time (0: on the road at reset)

    @classmethod
    def zeros(cls, n_envs: int, n_vehicles: int, idm_delta: float) -> HighwayParams:
        """A batch record before any reset (a reset writes every row of its env)."""
        shape = (n_envs, n_vehicles)
        return cls(
            idm=IdmParams(
                np.zeros(shape), np.zeros(shape), np.ones(shape), np.ones(shape), idm_delta
            ),
            inv_2_sqrt_ab_s2_per_m=np.zeros(shape),
            politeness=np.zeros(shape),
            gain_threshold_mps2=np.zeros(shape),
            strategic=np.zeros(shape, bool),
            zipper=np.zeros(shape, bool),
            merge_zone_m=np.zeros(shape),
            reported_cav=np.zeros(shape, bool),
            style=np.zeros(shape, np.int8),
            depart_s=np.zeros(shape),
        )


@dataclass(slots=True)
class HighwayCaches(EnvRows):
    """Quantities derived from state and parameters, kept between sub-steps.

    Each group is refreshed by one function of :mod:`.dynamics`, when its inputs may have
    changed (its docstring says when). Those refreshed on events
    only are part of a running batch's state: copy them along with it.
    """

    # dynamics.refresh_road_facts: at decisions and lane-change starts.
    desired_mps: np.ndarray = per_vehicle()  # float64 speed limit of the vehicle's segment
    inv_desired_s_per_m: np.ndarray = per_vehicle()  # float64 1 / max(desired_mps, 1e-3)
    end_x_m: np.ndarray = per_vehicle()  # float64 centre x at which the destination lane ends
    # dynamics.refresh_speed_bounds: at commands, resets, contacts and arrivals.
    v_lo_mps: np.ndarray = per_vehicle()  # float64 lowest speed a sub-step may reach
    v_hi_mps: np.ndarray = per_vehicle()  # float64 highest speed a sub-step may reach
    half_dt_active_s: np.ndarray = per_vehicle()  # float64 dt / 2 on the road, 0 off it
    # dynamics.refresh_leaders: in the envs marked in leaders_dirty.
    leader: np.ndarray = per_vehicle()  # intp nearest active vehicle ahead sharing a lane
    has_leader: np.ndarray = per_vehicle()  # bool ``leader`` is real
    guarded: np.ndarray = per_vehicle()  # bool an HDV behind an HDV leader (last-resort guard)
    screen: np.ndarray = per_vehicle()  # bool leader pair that can start a contact
    moving: np.ndarray = per_vehicle()  # bool in a lane change, on the road, not wrecked
    pairs_active: np.ndarray = per_pair()  # bool pairs that can start a contact
    leaders_dirty: np.ndarray = per_env()  # bool leaders must be searched again before a sub-step
    # Some heading was non-zero after the last sub-step (else zeroing it is skipped).
    heading_nonzero: bool = shared()

    @classmethod
    def zeros(cls, n_envs: int, n_vehicles: int) -> HighwayCaches:
        """Caches before any reset: every env's leaders are dirty."""
        shape = (n_envs, n_vehicles)
        return cls(
            desired_mps=np.zeros(shape),
            inv_desired_s_per_m=np.zeros(shape),
            end_x_m=np.zeros(shape),
            v_lo_mps=np.zeros(shape),
            v_hi_mps=np.zeros(shape),
            half_dt_active_s=np.zeros(shape),
            leader=np.zeros(shape, np.intp),
            has_leader=np.zeros(shape, bool),
            guarded=np.zeros(shape, bool),
            screen=np.zeros(shape, bool),
            moving=np.zeros(shape, bool),
            pairs_active=np.zeros((n_envs, n_vehicles, n_vehicles), bool),
            leaders_dirty=np.ones(n_envs, bool),
            heading_nonzero=False,
        )


class HighwaySim(Protocol):
    """What the highway backend's seams (:mod:`.insertion`, :mod:`.lanes`,
    :mod:`.dynamics`, :mod:`.export`) read and write of it: the records, the
    settings, and the constant arrays of the current vehicle window."""

    road: Map
    sim: SimConfig
    model: HighwayModel
    cooperative: CooperativeCavParams
    cav_mode: str
    tables: LaneTables
    n_envs: int
    dt_s: float
    state: HighwayState
    params: HighwayParams
    caches: HighwayCaches
    stats: dict[str, np.ndarray]  # (E,) int64 event counters each
    no_contact: np.ndarray  # (E, W, W) bool, all False
    not_self: np.ndarray  # (W, W) bool, j is not i
    own_index: np.ndarray  # (E, W) each vehicle's own index
    sides: np.ndarray  # (3,) lane offsets right, own, left
    min_accel_mps2: float
