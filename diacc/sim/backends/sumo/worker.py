"""The libsumo simulation that runs inside one worker process.

libsumo holds one simulation per process (a second start silently replaces the first), so every
:class:`~diacc.sim.backends.sumo.backend.SumoBackend` owns a worker process that runs
:func:`worker_main`. The worker owns a :class:`SumoSim` and answers three
requests over a ``multiprocessing.connection.Connection`` (a socket pair
whose child end is passed as a file descriptor number on the command line):
pickled ``("reset", seed, population)`` and ``("close",)``, and the step
request of :mod:`.wire` (lane and speed changes as raw bytes). Replies are
states in :mod:`.wire`'s encoding or a pickled ``("err", one-line message)``.

Time: SUMO runs at ``step_s / substeps`` seconds per simulation step (0.1 s
with the defaults), the same integration step as the highway backend, so
that car following, lane-change manoeuvres (``--lanechange.duration`` =
0.8 decision steps) and collisions are resolved within a decision step.
State is read once per decision step through libsumo subscriptions (one call
for all vehicles), arrivals with it (:meth:`SumoSim._read_state`); collisions
are gathered after every substep, since SUMO reports only the last one's.
"""

from __future__ import annotations

import pickle
import types
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from diacc.errors import DiaccError
from diacc.sim.backends.sumo import wire
from diacc.sim.backends.sumo.net import ROUTE_ID, lane_ids
from diacc.sim.backends.sumo.vtypes import CAV_TYPE, HDV_TYPES
from diacc.sim.kinematics import lane_change_reach_m
from diacc.sim.maps import Map
from diacc.sim.scenario import Population
from diacc.sim.settings import SimConfig
from diacc.sim.state import PER_VEHICLE_FIELDS, TrafficState

#: laneChangeMode of commanded CAVs: 0 = no lane change of SUMO's own (strategic,
#: cooperative, speed gain, keep right all off) and TraCI changes executed without
#: SUMO's gap checks (bits 8-9 = 0). So the policy alone chooses lane changes,
#: without built-in safety, and SUMO never moves a CAV out of an ending lane: it
#: stops at the lane end, as on the highway backend (the authors' 1109 leaves
#: strategic, speed-gain and keep-right changes on, which would let SUMO steer the
#: agent).
CAV_LANE_CHANGE_MODE = 0
#: speedMode of commanded CAVs: no safe-speed, acceleration or right-of-way checks.
CAV_SPEED_MODE = 0
#: SUMO's own modes, for a CAV that drives itself (no command this step).
SUMO_DEFAULT_SPEED_MODE = 31
SUMO_DEFAULT_LANE_CHANGE_MODE = 1621
#: laneChangeMode of a CAV in the step it enters (demand): SUMO's own car following,
#: but no lane change of SUMO's own. A change LC2013 began then (0.8 s long) went on
#: after the CAV was handed to its commands, unseen by PSAR (the state still showed the
#: old lane), and put the CAV behind a queue it could not stop for (issue 57).
ENTERING_LANE_CHANGE_MODE = 0
#: Lane-change manoeuvre time as a fraction of a decision step: long enough for
#: a readable heading (SUMO keeps heading 0 for instant changes), short enough
#: that a change commanded at the start of a step ends within it (base.py).
LANE_CHANGE_FRACTION = 0.8
#: Lateral offset (m) from the lane's centre line within which a vehicle is on it.
CENTRE_LINE_TOL_M = 1e-6

#: SUMO's ``--seed`` is a signed 32-bit integer; diacc's seeds are 32-bit unsigned
#: (numpy's), so a seed from 2^31 on is taken modulo 2^31 (smaller ones as they are).
SUMO_SEEDS = 2**31
#: libsumo.constants names of the vehicle variables a TrafficState is built
#: from, subscribed for every vehicle and read in one call per decision step.
STATE_VARIABLES = (
    "VAR_LANE_ID", "VAR_LANEPOSITION", "VAR_LANEPOSITION_LAT", "VAR_SPEED", "VAR_ANGLE",
)  # fmt: skip


@dataclass(frozen=True)
class WorkerSpec:
    """Everything a worker needs to build its simulation (picklable)."""

    road: Map
    sim: SimConfig
    net_path: Path
    route_path: Path
    vtypes_path: Path


class SimulationError(DiaccError, RuntimeError):
    """The simulation cannot go on (failed insertion...); one-line message."""


class SumoSim:
    """One libsumo simulation of a map; returns :class:`TrafficState` arrays."""

    def __init__(self, spec: WorkerSpec) -> None:
        import libsumo  # imported here: only worker processes may load libsumo

        self.ls = libsumo
        self.state_vars = [getattr(libsumo.constants, name) for name in STATE_VARIABLES]
        self.spec = spec
        self.road = spec.road
        self.sim = spec.sim
        self.dt_s = spec.sim.step_s / spec.sim.substeps
        self.started = False
        self.lane_at = lane_ids(self.road)  # {SUMO lane id: (segment, absolute lane)}
        self.edge_start_m = self.road.segment_starts_m  # (S,)
        self.first_lane = np.array(
            [self.road.first_lane(s) for s in range(len(self.road.segments))], np.int16
        )  # (S,)
        self.n_lanes = np.array([seg.lanes for seg in self.road.segments], np.int16)  # (S,)
        self.speed_limit = np.array([seg.speed_limit_mps for seg in self.road.segments])  # (S,)
        self.version = ""
        self.state: TrafficState | None = None

    # ---- lifecycle -----------------------------------------------------
    def _args(self, seed: int, demand: bool = False) -> list[str]:
        s = self.spec
        # The release's slots are 3 m apart at 10 m/s (the paper-like start): physically
        # free but closer than IDM's safe gap, so only overlap is checked; the cars
        # brake in the first steps, as on the highway backend. Vehicles entering over
        # time (demand) get SUMO's full checks: one enters when its entry is safe.
        checks = "all" if demand else "collision"
        return [
            "-n", str(s.net_path),
            "-a", str(s.vtypes_path),
            "-r", str(s.route_path),
            "--step-length", f"{self.dt_s}",
            "--seed", str(int(seed) % SUMO_SEEDS),
            "--collision.action", "warn",
            "--collision.check-junctions", "true",
            "--time-to-teleport", "-1",
            "--insertion-checks", checks,
            "--lanechange.duration", f"{LANE_CHANGE_FRACTION * self.sim.step_s}",
            "--default.action-step-length", f"{self.dt_s}",
            "--no-step-log", "true",
            "--no-warnings", "true",
            "--duration-log.disable", "true",
        ]  # fmt: skip

    def load(self, seed: int, demand: bool = False) -> None:
        """(Re)start SUMO with a seed; ``load`` is much cheaper than a new ``start``."""
        if self.started:
            self.ls.load(self._args(seed, demand))
        else:
            import sumolib

            self.ls.start([sumolib.checkBinary("sumo"), *self._args(seed, demand)])
            self.started = True
            self.version = str(self.ls.simulation.getVersion()[1])

    def close(self) -> None:
        if self.started:
            self.ls.close()
            self.started = False

    # ---- reset ---------------------------------------------------------
    def reset(self, seed: int, pop: Population) -> TrafficState:
        """Insert exactly ``pop`` and, in a release, check that every vehicle is on the road.

        Vehicles of a demand scenario depart at their ``depart_s`` (SUMO delays
        one whose entry is not yet safe) and are pending until then. Returns the
        simulation's own state, which the next step updates in place (the worker
        encodes it before that; other callers copy it).
        """
        self.demand = bool(np.any(pop.depart_s > 0.0))
        self.load(seed, self.demand)
        n = pop.n_vehicles
        self.ids = [f"v{i}" for i in range(n)]
        self.index = {vid: i for i, vid in enumerate(self.ids)}
        self.is_cav = pop.is_cav.copy()
        self.commanded = pop.is_cav & (self.spec.sim.cav_mode == "commanded")  # (V,)
        self.self_driving = np.zeros(n, bool)  # (V,) commanded CAVs now without a command
        self.entering = np.zeros(n, bool)  # (V,) CAVs that entered in the last step (demand)
        self.removed = np.zeros(n, bool)  # (V,) taken off the road after a collision
        length_m = self.sim.vehicle_length_m
        front_m = pop.x_m + 0.5 * length_m  # (V,) SUMO departPos is the front bumper
        sumo_lane = pop.lane - self.first_lane[0]  # (V,)
        veh = self.ls.vehicle
        for i, vid in enumerate(self.ids):
            type_id = CAV_TYPE if pop.is_cav[i] else HDV_TYPES[pop.style[i]]
            veh.add(
                vid, ROUTE_ID, typeID=type_id, depart=f"{pop.depart_s[i]:.3f}",
                departLane=str(int(sumo_lane[i])),
                departPos=f"{front_m[i]:.3f}", departSpeed=f"{pop.speed_mps[i]:.3f}",
            )  # fmt: skip
        self.ls.simulationStep()  # insertion happens in SUMO's first step, before any move
        on_road = set(veh.getIDList())
        missing = [vid for vid in self.ids if vid not in on_road]
        if missing and not self.demand:
            raise SimulationError(
                f"SUMO did not insert {len(missing)} of {n} vehicles ({', '.join(missing[:5])}"
                f"{'...' if len(missing) > 5 else ''}) on map {self.road.name!r}: "
                "the starting slots are too tight for the vehicle types"
            )
        self._subscribe([vid for vid in self.ids if vid in on_road])
        self.state = TrafficState(  # the one simulation as a batch of one: (1, V) arrays
            time_s=np.zeros(1),
            step=np.zeros(1, np.int64),
            vehicle_id=np.arange(n, dtype=np.int32)[None],
            x_m=pop.x_m.astype(np.float64)[None],  # pending vehicles (demand) wait at their slot
            y_m=self.road.lane_center_y_m(pop.lane).astype(np.float64)[None],
            speed_mps=pop.speed_mps.astype(np.float64)[None],
            accel_mps2=np.zeros((1, n)),
            heading_rad=np.zeros((1, n)),
            lane=pop.lane.astype(np.int16)[None],
            segment=np.zeros((1, n), np.int16),
            length_m=np.full((1, n), length_m),
            width_m=np.full((1, n), self.sim.vehicle_width_m),
            is_cav=pop.is_cav.astype(bool)[None],
            style=pop.style.astype(np.int8)[None],
            active=np.zeros((1, n), bool),  # set by _read_state
            arrived=np.zeros((1, n), bool),
            collisions=np.zeros((0, 3), np.int32),
            arrivals=np.zeros((0, 2), np.int32),
        )
        self._read_state()
        self.state.accel_mps2[:] = 0.0
        return self.state

    # ---- step ----------------------------------------------------------
    def step(self, lane_change: np.ndarray, speed_change_mps: np.ndarray) -> TrafficState:
        """Apply CAV commands, advance one decision step, return the state (as :meth:`reset`)."""
        st = self.state
        if st is None:
            raise SimulationError("step() called before reset()")
        self._command(lane_change, speed_change_mps)
        # Colliding pairs stay in contact for several substeps: collect the ids
        # once per pair and map them to indices after the loop.
        contacts: set[tuple[str, str]] = set()
        sim = self.ls.simulation
        for _ in range(self.sim.substeps):
            sim.step()
            contacts.update((c.collider, c.victim) for c in sim.getCollisions())
            if self.demand:
                self._subscribe(sim.getDepartedIDList())
        pairs = set()
        for collider, victim in contacts:
            a, b = self.index.get(collider), self.index.get(victim)
            if a is not None and b is not None:
                pairs.add((min(a, b), max(a, b)))
        rows = [(0, a, b) for a, b in sorted(pairs)]  # (env 0, i, j)
        st.collisions = np.array(rows, np.int32).reshape(-1, 3)
        if self.sim.on_collision == "remove":
            self._remove(sorted({i for pair in pairs for i in pair}))
        prev_speed = st.speed_mps.copy()
        st.step += 1
        st.time_s = st.step * self.sim.step_s
        self._read_state()
        st.accel_mps2 = np.where(st.active, (st.speed_mps - prev_speed) / self.sim.step_s, 0.0)
        return st

    def _remove(self, crashed: list[int]) -> None:
        """Take the vehicles that collided this step off the road (``on_collision =
        "remove"``): gone, never arrived (:meth:`_read_state` tells them apart).

        A vehicle that collided in one substep may have reached its route's end in a
        later one: SUMO no longer knows it, so there is nothing to take off, but its
        trip still ended in the crash, as on highway, where wrecks leave at once.
        """
        crashed = [i for i in crashed if not self.removed[i]]
        on_road = set(self.ls.vehicle.getIDList()) if crashed else set()
        for i in crashed:
            if self.ids[i] in on_road:
                self.ls.vehicle.unsubscribe(self.ids[i])  # else the next step fails on it
                self.ls.vehicle.remove(self.ids[i])
            self.removed[i] = True

    def _subscribe(self, vids) -> None:
        """Subscribe vehicles that just entered. A release's CAVs are handed to the
        commands at once; a CAV entering later drives itself until its first command."""
        veh = self.ls.vehicle
        for vid in vids:
            veh.subscribe(vid, self.state_vars)
            i = self.index[vid]
            if self.commanded[i] and not self.demand:
                veh.setSpeedMode(vid, CAV_SPEED_MODE)
                veh.setLaneChangeMode(vid, CAV_LANE_CHANGE_MODE)
            elif self.commanded[i]:  # keeps its lane until the step after it entered
                veh.setLaneChangeMode(vid, ENTERING_LANE_CHANGE_MODE)
            self.self_driving[i] = self.entering[i] = self.commanded[i] and self.demand

    def _command(self, lane_change: np.ndarray, speed_change_mps: np.ndarray) -> None:
        """Send each active commanded CAV its step's speed, and its lane change if any.

        np.minimum/np.maximum instead of np.clip, which costs several
        microseconds per call on arrays this small (same values).
        """
        st = self._rows()
        # NaN: no command, the CAV drives itself with SUMO's own models (base.py).
        free = self.commanded & st.active & np.isnan(speed_change_mps)  # (V,)
        veh = self.ls.vehicle
        for i in np.flatnonzero(free & ~self.self_driving).tolist():
            veh.setSpeedMode(self.ids[i], SUMO_DEFAULT_SPEED_MODE)
            veh.setLaneChangeMode(self.ids[i], SUMO_DEFAULT_LANE_CHANGE_MODE)
        for i in np.flatnonzero(free & self.entering & st.active).tolist():  # no slot for it
            veh.setLaneChangeMode(self.ids[i], SUMO_DEFAULT_LANE_CHANGE_MODE)
        self.entering[:] = False
        for i in np.flatnonzero(~free & self.self_driving & st.active).tolist():
            veh.setSpeedMode(self.ids[i], CAV_SPEED_MODE)
            veh.setLaneChangeMode(self.ids[i], CAV_LANE_CHANGE_MODE)
        self.self_driving = free
        cav = np.flatnonzero(self.commanded & st.active & ~free)  # (C,)
        if cav.size == 0:
            return
        seg = st.segment[cav]
        # Speed: target at the end of the step, within the CAV's limits.
        cav_p, v, step_s = self.sim.cav, st.speed_mps[cav], self.sim.step_s
        goal = np.minimum(np.maximum(v + speed_change_mps[cav], 0.0), self.speed_limit[seg])
        goal = np.minimum(
            np.maximum(goal, v - cav_p.decel_mps2 * step_s), v + cav_p.accel_mps2 * step_s
        )  # (C,)
        veh, ids = self.ls.vehicle, self.ids
        for i, goal_mps in zip(cav.tolist(), goal.tolist(), strict=True):
            veh.slowDown(ids[i], goal_mps, step_s)
        # Lane changes: only those the road allows (the rule PSAR and highway apply).
        offset = np.minimum(np.maximum(lane_change[cav], -1), 1).astype(np.int16)  # (C,)
        if not offset.any():
            return
        reach_m = lane_change_reach_m(v, step_s, st.length_m[cav])
        valid = self.road.lane_change_allowed(seg, st.lane[cav], offset, st.x_m[cav], reach_m)
        target = st.lane[cav] - self.first_lane[seg] + offset  # (C,) SUMO lane index
        for i, lane in zip(cav[valid].tolist(), target[valid].tolist(), strict=True):
            veh.changeLane(ids[i], lane, step_s)

    # ---- state ---------------------------------------------------------
    def _rows(self) -> types.SimpleNamespace:
        """The one simulation's (V,) rows of the state (views) and its vehicle count."""
        state = self.state
        rows = {name: getattr(state, name)[0] for name in PER_VEHICLE_FIELDS}
        return types.SimpleNamespace(**rows, n_vehicles=state.n_vehicles)

    def _read_state(self) -> None:
        """Copy every active vehicle's subscribed variables into the state arrays.

        Vehicles leave the road only at the route end (no teleports, collisions
        only warn) or when :meth:`_remove` takes them off, and a vehicle's
        subscription ends when it leaves: so the active vehicles missing from the
        results, and not removed, are this step's arrivals,
        without asking SUMO for its arrived list after every substep.
        """
        st = self._rows()  # views: writes go to the state
        results = {  # {id: {var: value}}; a removed vehicle's last results may linger
            vid: r
            for vid, r in self.ls.vehicle.getAllSubscriptionResults().items()
            if not self.removed[self.index[vid]]
        }
        lane_id, pos, lat, speed, angle = self.state_vars
        index, lane_at = self.index, self.lane_at
        try:
            rows = [
                (index[vid], *lane_at[r[lane_id]], r[pos], r[lat], r[speed], r[angle])
                for vid, r in results.items()
            ]
        except KeyError as exc:  # the network has no junction-internal lanes (net.py)
            raise SimulationError(
                f"a vehicle is on SUMO lane {exc.args[0]!r}, which is not a lane of map "
                f"{self.road.name!r}"
            ) from None
        data = np.array(rows, dtype=np.float64).reshape(-1, 7)  # (A, 7)
        idx = data[:, 0].astype(np.int64)
        present = np.zeros(st.n_vehicles, bool)
        present[idx] = True
        arrivals = np.flatnonzero(st.active & ~present & ~self.removed).astype(np.int32)  # (A,)
        self.state.arrivals = np.stack([np.zeros_like(arrivals), arrivals], axis=1)
        st.arrived[arrivals] = True
        st.active[:] = present  # pending vehicles (demand) become active when they depart
        seg = data[:, 1].astype(np.int16)
        abs_lane = data[:, 2].astype(np.int16)
        st.segment[idx] = seg
        st.lane[idx] = abs_lane
        st.x_m[idx] = self.edge_start_m[seg] + data[:, 3] - 0.5 * st.length_m[idx]
        st.y_m[idx] = (abs_lane + 0.5) * self.road.lane_width_m + data[:, 4]
        st.speed_mps[idx] = data[:, 5]
        # SUMO angle: compass degrees, 90 = along +x (the route); ours: radians, left positive.
        # SUMO turns a vehicle by its last movement and keeps that angle while it (nearly)
        # stands: a CAV that changed lanes from standstill (its change completes within
        # the step) stood askew (35 degrees) on its new lane's centre line for as long as
        # it waited, which shortened every gap PSAR measures to it and could block the
        # lane change of the CAV beside it forever (issue 44). The roads are straight, so
        # a vehicle on its lane's centre line (no change under way) points along it.
        straight = np.abs(data[:, 4]) < CENTRE_LINE_TOL_M
        st.heading_rad[idx] = np.where(straight, 0.0, np.deg2rad(90.0 - data[:, 6]))


def worker_main(conn) -> None:  # pragma: no cover - runs in a child process
    """Serve reset/step/close requests until ``close`` or until the parent goes away.

    The first message is ``("spec", WorkerSpec)``; the reply carries the SUMO version.
    """
    sim = None
    try:
        try:
            kind, spec = conn.recv()
            if kind != "spec":
                raise SimulationError(f"expected a spec message, got {kind!r}")
            sim = SumoSim(spec)
            sim.load(0)
        except Exception as exc:  # noqa: BLE001 - reported to the parent as one line
            conn.send(("err", f"SUMO failed to start: {type(exc).__name__}: {exc}"))
            return
        conn.send(("ok", sim.version))
        while True:
            message = conn.recv_bytes()
            try:
                if wire.is_step_request(message):
                    conn.send_bytes(wire.encode_state(sim.step(*wire.decode_step_request(message))))
                    continue
                msg = pickle.loads(message)
                if msg[0] == "close":
                    break
                if msg[0] == "reset":
                    conn.send_bytes(wire.encode_state(sim.reset(msg[1], msg[2])))
                else:
                    conn.send(("err", f"unknown request {msg[0]!r}"))
            except Exception as exc:  # noqa: BLE001 - reported to the parent as one line
                text = str(exc).strip().splitlines()
                conn.send(("err", f"{type(exc).__name__}: {text[0] if text else ''}"))
    except (EOFError, ConnectionError, KeyboardInterrupt):
        # Parent gone (end of file, or a reset when it died with a reply unread) or
        # interrupted with it (Ctrl-C reaches the whole process group): just exit.
        pass
    finally:
        if sim is not None:
            sim.close()


if __name__ == "__main__":  # pragma: no cover - the worker process entry point
    import sys
    from multiprocessing.connection import Connection

    # Import by name so that pickled specs and this code share one module object.
    from diacc.sim.backends.sumo.worker import worker_main as _main

    _main(Connection(int(sys.argv[1])))
