"""Episode metrics of paper Tables II-III from a sequence of TrafficStates.

Feed :class:`EpisodeRecorder` every state of an episode (the reset state
too, so t = 0 speeds count) and, optionally, the PSAR result of each step.
Each call appends a few arrays (no loop over vehicles); :meth:`summary`
reduces them to :class:`EpisodeMetrics`.

Definitions:

* Speeds: one sample per (vehicle, recorded state) with the vehicle active.
  ``std_speed_mps`` is the population standard deviation (ddof = 0) of those
  samples, as "mean +- std over all vehicles and steps" in the paper.
* ``p_we`` / ``p_sce``: share of the vehicles ever seen on the road that had
  at least one waiting event / safety-critical event
  (:func:`diacc.envs.safety.waiting_events`, :func:`diacc.envs.safety.safety_critical_events`).
* ``n_collisions``: distinct unordered vehicle pairs that collided during the
  episode (a pair still overlapping on the next step is not counted twice);
  ``n_hdv_collisions`` counts the pairs of two HDVs among them.
* ``arrived_fraction``: vehicles that reached the route end / vehicles seen.
  Travel time = time of the first state marking a vehicle arrived minus the
  time of the first state it was seen active in.
* Flow (how the bottleneck serves the traffic as a whole):
  ``throughput_vph``: vehicles seen past the end of the last reduction segment
  (or arrived), per hour of the episode (first to last recorded state; nan on
  a map without a reduction). ``total_delay_s``: vehicle-seconds lost against
  free-flow travel at each segment's speed limit, summed over the vehicles
  seen: time on the road (to arrival, or to the episode's end for vehicles
  still on it) minus the time the distance they covered takes at the limits;
  ``delay_per_vehicle_s`` divides it by the vehicles seen.
  ``mean_arrived_speed_mps``: mean of the speed samples of vehicles that
  arrived; ``never_arrived_fraction`` = 1 - ``arrived_fraction``.
* PSAR fire rate per rule: CAV decisions where the rule took effect
  (:attr:`diacc.envs.psar.PSARResult.rule_mask`) / decisions of active CAVs.
* Warm-up (``warmup_s``, demand scenarios): states before it add no speed
  sample, event, collision or PSAR count, and vehicles count as seen only
  once on the road after it; travel times are those of vehicles that entered
  after it (so none is cut short). Flows cover the measured window only:
  throughput counts the vehicles passing the bottleneck's end after the
  warm-up per hour of the window, the delay is that of each vehicle's time on
  the road within the window. 0 (the default) measures everything.
"""

from __future__ import annotations

import csv
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from diacc.config import EventConfig
from diacc.envs.psar import RULE_NAMES, PSARResult, rule_counts
from diacc.envs.safety import safety_critical_events, waiting_events
from diacc.errors import DiaccError
from diacc.sim.maps import SEGMENT_KINDS, Map
from diacc.sim.state import TrafficState


class MetricsError(DiaccError, ValueError):
    """Inconsistent input to the recorder (vehicle count changed...); one line."""


@dataclass
class EpisodeMetrics:
    """One episode's summary (paper Tables II-III); nan where undefined."""

    mean_speed_mps: float
    std_speed_mps: float
    mean_cav_speed_mps: float
    mean_hdv_speed_mps: float
    mean_speed_by_kind_mps: dict[str, float]  # segment kind -> mean speed (nan if unvisited)
    p_we: float
    p_sce: float
    n_collisions: int
    n_hdv_collisions: int  # of those, pairs of two HDVs
    arrived_fraction: float
    mean_travel_time_s: float
    episode_steps: int
    n_vehicles: int  # vehicles seen on the road
    psar_decisions: int  # active-CAV decisions that went through PSAR
    psar_fire_rate: dict[str, float]  # rule name -> fraction of those decisions
    throughput_vph: float  # vehicles past the bottleneck's end per hour
    total_delay_s: float  # vehicle-seconds lost against the speed limits
    delay_per_vehicle_s: float
    mean_arrived_speed_mps: float  # speed samples of vehicles that arrived
    never_arrived_fraction: float

    def as_dict(self) -> dict:
        """Plain dict (for JSON / TensorBoard logging)."""
        return asdict(self)


@dataclass
class SpeedSamples:
    """Per-(vehicle, step) speed samples as columns, for CSV and box plots."""

    vehicle: np.ndarray  # (S,) int32
    step: np.ndarray  # (S,) int32
    time_s: np.ndarray  # (S,) float64
    speed_mps: np.ndarray  # (S,) float64
    segment_kind: np.ndarray  # (S,) int8 index into diacc.sim.maps.SEGMENT_KINDS
    is_cav: np.ndarray  # (S,) bool

    COLUMNS = ("vehicle", "step", "time_s", "speed_mps", "segment_kind", "is_cav")

    def rows(self) -> list[tuple]:
        """Rows (vehicle, step, time_s, speed_mps, segment kind name, is_cav)."""
        kinds = np.asarray(SEGMENT_KINDS, dtype=object)[self.segment_kind]
        return list(
            zip(
                self.vehicle.tolist(),
                self.step.tolist(),
                self.time_s.tolist(),
                self.speed_mps.tolist(),
                kinds.tolist(),
                self.is_cav.tolist(),
                strict=True,
            )
        )

    def to_csv(self, path: str | Path) -> None:
        """Write the rows with a header line."""
        with open(path, "w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(self.COLUMNS)
            writer.writerows(self.rows())


class EpisodeRecorder:
    """Accumulates one episode's per-vehicle records, step by step.

    Args:
        road: the map (segment kinds for per-kind speeds).
        events: thresholds of the waiting / safety-critical event detectors.
    """

    def __init__(self, road: Map, events: EventConfig | None = None, warmup_s: float = 0.0) -> None:
        self.road = road
        self.events = events or EventConfig()
        self.warmup_s = warmup_s
        self._kind_of_segment = np.array(
            [SEGMENT_KINDS.index(s.kind) for s in road.segments], dtype=np.int8
        )  # (S,)
        self._n: int | None = None
        self._chunks: list[tuple[np.ndarray, ...]] = []
        self._collision_pairs: list[np.ndarray] = []
        self._psar_counts = np.zeros(len(RULE_NAMES) - 1, dtype=np.int64)
        self._psar_decisions = 0
        self._first_step: int | None = None
        self._last_step = 0
        self._last_time_s = 0.0
        reductions = [i for i, seg in enumerate(road.segments) if seg.kind.startswith("reduction")]
        #: x past which a vehicle has crossed the bottleneck (nan: no reduction segment)
        self._bottleneck_end_m = (
            float(road.segment_ends_m[reductions[-1]]) if reductions else float("nan")
        )
        limits = np.array([seg.speed_limit_mps for seg in road.segments])  # (S,)
        lengths = np.array([seg.length_m for seg in road.segments])  # (S,)
        #: free-flow time to reach each segment boundary from the route start
        self._edges_m = np.concatenate([[0.0], np.cumsum(lengths)])  # (S + 1,)
        self._free_time_s = np.concatenate([[0.0], np.cumsum(lengths / limits)])  # (S + 1,)

    def _init_vehicles(self, n: int) -> None:
        self._n = n
        self._is_cav = np.zeros(n, dtype=bool)  # (V,)
        self._seen = np.zeros(n, dtype=bool)  # (V,)
        self._waited = np.zeros(n, dtype=bool)  # (V,)
        self._sce = np.zeros(n, dtype=bool)  # (V,)
        self._arrived = np.zeros(n, dtype=bool)  # (V,)
        self._entered = np.zeros(n, dtype=bool)  # (V,) on the road at some recorded state
        self._first_time_s = np.full(n, np.nan)  # (V,)
        self._arrival_time_s = np.full(n, np.nan)  # (V,)
        self._window_time_s = np.full(n, np.nan)  # (V,) first measured on the road
        self._window_start_s: float | None = None
        self._passed_before = np.zeros(n, dtype=bool)  # (V,) past the end at window start
        self._first_x_m = np.full(n, np.nan)  # (V,)
        self._last_x_m = np.full(n, np.nan)  # (V,)
        self._passed = np.zeros(n, dtype=bool)  # (V,) crossed the bottleneck's end

    def record(
        self,
        state: TrafficState,
        psar: PSARResult | None = None,
        critical: np.ndarray | None = None,
    ) -> None:
        """Add one state (and the PSAR result of the step that led to it, if any).

        ``critical``: (V,) bool, ``safety_critical_events(state, events).any`` if the
        caller has it already (a batch of envs detects them in one call).
        """
        if self._n is None:
            self._init_vehicles(state.n_vehicles)
        elif state.n_vehicles != self._n:
            raise MetricsError(
                f"state has {state.n_vehicles} vehicles, the episode started with {self._n}"
            )
        if np.any(state.segment >= self._kind_of_segment.shape[0]):
            raise MetricsError(
                f"segment index outside the map's {self._kind_of_segment.shape[0]} segments"
            )
        if self._first_step is None:
            self._first_step = state.step
            self._is_cav = state.is_cav.copy()
        self._last_step = state.step
        new = state.active & ~self._entered
        self._first_time_s[new] = state.time_s
        self._entered |= state.active
        self._last_time_s = float(state.time_s)
        if state.time_s < self.warmup_s - 1e-9:
            return
        if self._window_start_s is None:  # first measured state: flows count from here
            self._window_start_s = float(state.time_s)
            if self.warmup_s > 0:  # those passed during the warm-up
                self._passed_before = state.active & (state.x_m >= self._bottleneck_end_m)

        idx = np.flatnonzero(state.active)  # (A,)
        self._chunks.append(
            (
                idx.astype(np.int32),
                np.full(idx.shape, state.step, dtype=np.int32),
                np.full(idx.shape, state.time_s, dtype=np.float64),
                state.speed_mps[idx].astype(np.float64),
                self._kind_of_segment[state.segment[idx]],
                state.is_cav[idx].copy(),
            )
        )
        new = state.active & ~self._seen
        self._window_time_s[new] = state.time_s
        self._first_x_m[new] = state.x_m[new]
        self._last_x_m[state.active] = state.x_m[state.active]
        self._passed |= state.arrived | (state.active & (state.x_m >= self._bottleneck_end_m))
        self._seen |= state.active
        self._waited |= waiting_events(state, self.events)
        if critical is None:
            critical = safety_critical_events(state, self.events).any
        self._sce |= critical
        newly_arrived = state.arrived & ~self._arrived
        self._arrival_time_s[newly_arrived] = state.time_s
        self._arrived |= state.arrived
        if state.collisions.shape[0]:
            self._collision_pairs.append(np.sort(state.collisions, axis=1))
        if psar is not None:
            self._psar_counts += rule_counts(psar.rule_mask[psar.active])
            self._psar_decisions += int(np.count_nonzero(psar.active))

    def speed_samples(self) -> SpeedSamples:
        """All recorded speed samples of active vehicles, in recording order.

        Empty when every state so far lay in the warm-up: a demand episode that a
        collision ended before ``warmup_s`` still has its summary (measuring nothing).
        """
        if self._first_step is None:
            raise MetricsError("no state recorded yet")
        if not self._chunks:
            dtypes = (np.int32, np.int32, np.float64, np.float64, np.int8, bool)
            return SpeedSamples(*(np.zeros(0, dtype) for dtype in dtypes))
        cols = [np.concatenate(c) for c in zip(*self._chunks, strict=True)]
        return SpeedSamples(*cols)

    def summary(self) -> EpisodeMetrics:
        """Reduce the records to :class:`EpisodeMetrics`."""
        samples = self.speed_samples()
        speed = samples.speed_mps
        n_seen = int(np.count_nonzero(self._seen))
        by_kind = {
            kind: _mean(speed[samples.segment_kind == k]) for k, kind in enumerate(SEGMENT_KINDS)
        }
        pairs = np.unique(
            np.concatenate([np.zeros((0, 2), np.int32), *self._collision_pairs]), axis=0
        )
        n_collisions = int(pairs.shape[0])
        n_hdv_collisions = int(np.count_nonzero(~self._is_cav[pairs].any(axis=1)))
        travel_s = self._arrival_time_s - self._first_time_s  # (V,) nan if not both
        travel_s[self._first_time_s < self.warmup_s - 1e-9] = np.nan  # entered in the warm-up
        decisions = self._psar_decisions
        fire = {
            name: (float(count) / decisions if decisions else float("nan"))
            for name, count in zip(RULE_NAMES[1:], self._psar_counts.tolist(), strict=True)
        }
        arrived = self._arrived & self._seen  # (V,)
        return EpisodeMetrics(
            mean_speed_mps=_mean(speed),
            std_speed_mps=float(speed.std()) if speed.size else float("nan"),
            mean_cav_speed_mps=_mean(speed[samples.is_cav]),
            mean_hdv_speed_mps=_mean(speed[~samples.is_cav]),
            mean_speed_by_kind_mps=by_kind,
            p_we=_share(self._waited & self._seen, n_seen),
            p_sce=_share(self._sce & self._seen, n_seen),
            n_collisions=n_collisions,
            n_hdv_collisions=n_hdv_collisions,
            arrived_fraction=_share(self._arrived & self._seen, n_seen),
            mean_travel_time_s=_mean(travel_s[np.isfinite(travel_s)]),
            episode_steps=int(self._last_step - (self._first_step or 0)),
            n_vehicles=n_seen,
            psar_decisions=decisions,
            psar_fire_rate=fire,
            **self._flow(samples, arrived, n_seen),
        )

    def _flow(self, samples: SpeedSamples, arrived: np.ndarray, n_seen: int) -> dict:
        """The flow fields of :class:`EpisodeMetrics` (module docstring)."""
        duration_h = (self._last_time_s - (self._window_start_s or 0.0)) / 3600.0
        n_passed = int(np.count_nonzero(self._passed & self._seen & ~self._passed_before))
        throughput = (
            n_passed / duration_h
            if duration_h > 0 and np.isfinite(self._bottleneck_end_m)
            else float("nan")
        )
        seen = self._seen  # (V,)
        end_time_s = np.where(arrived, self._arrival_time_s, self._last_time_s)  # (V,)
        end_x_m = np.where(arrived, self._edges_m[-1], self._last_x_m)  # (V,)
        free_s = self._free_flow_s(end_x_m[seen]) - self._free_flow_s(self._first_x_m[seen])
        total_delay = float(np.sum(end_time_s[seen] - self._window_time_s[seen] - free_s))
        arrived_samples = arrived[samples.vehicle]  # (S,)
        return {
            "throughput_vph": throughput,
            "total_delay_s": total_delay,
            "delay_per_vehicle_s": total_delay / n_seen if n_seen else float("nan"),
            "mean_arrived_speed_mps": _mean(samples.speed_mps[arrived_samples]),
            "never_arrived_fraction": _share(seen & ~arrived, n_seen),
        }

    def _free_flow_s(self, x_m: np.ndarray) -> np.ndarray:
        """Free-flow time (s) from the route start to ``x_m`` at the segments' limits."""
        return np.interp(x_m, self._edges_m, self._free_time_s)


def _mean(values: np.ndarray) -> float:
    return float(values.mean()) if values.size else float("nan")


def _share(flags: np.ndarray, n: int) -> float:
    return float(np.count_nonzero(flags)) / n if n else float("nan")
