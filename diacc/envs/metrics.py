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
import io
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from diacc.config import EventConfig
from diacc.envs.psar import RULE_BIT_VALUES, RULE_NAMES, PSARResult
from diacc.envs.safety import safety_critical_events, waiting_events
from diacc.errors import DiaccError
from diacc.fileio import atomic_write
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
        text = io.StringIO(newline="")
        writer = csv.writer(text)
        writer.writerow(self.COLUMNS)
        writer.writerows(self.rows())
        atomic_write(Path(path), text.getvalue())


class EpisodeRecorder:
    """Accumulates the per-vehicle records of E episodes side by side, step by step.

    One recorder serves a batch of E envs (the rows of a :class:`TrafficState`
    batch, each with its own episode: :meth:`start` begins new ones in some rows
    while the others go on) or a single env (E = 1, fed batches of one). Every
    :meth:`record` is a few array operations over all rows, so a batch of envs
    is not recorded one env at a time.

    Args:
        road: the map (segment kinds for per-kind speeds).
        events: thresholds of the waiting / safety-critical event detectors.
        warmup_s: states before this time measure nothing (demand scenarios).
        n_envs: E, the episodes recorded side by side.
    """

    def __init__(
        self,
        road: Map,
        events: EventConfig | None = None,
        warmup_s: float = 0.0,
        n_envs: int = 1,
    ) -> None:
        self.road = road
        self.events = events or EventConfig()
        self.warmup_s = warmup_s
        self.n_envs = n_envs
        self._kind_of_segment = np.array(
            [SEGMENT_KINDS.index(s.kind) for s in road.segments], dtype=np.int8
        )  # (S,)
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
        self._n: int | None = None
        #: speed samples of every measured state: (env, vehicle, step, time, speed, kind,
        #: is_cav) columns of all rows at once; ``_chunk0`` counts the chunks dropped
        self._chunks: list[tuple[np.ndarray, ...]] = []
        self._chunk0 = 0
        self._episode_chunk = np.zeros(n_envs, np.int64)  # (E,) first chunk of each episode
        self._joined_key: tuple[int, int] | None = None  # chunks joined in ``_joined``
        self._joined: list[np.ndarray] = []
        self._collision_pairs: list[list[np.ndarray]] = [[] for _ in range(n_envs)]
        self._psar_counts = np.zeros((n_envs, len(RULE_NAMES) - 1), dtype=np.int64)  # (E, 4)
        self._psar_decisions = np.zeros(n_envs, np.int64)  # (E,)
        self._first_step = np.full(n_envs, -1, np.int64)  # (E,) -1: nothing recorded yet
        self._last_step = np.zeros(n_envs, np.int64)  # (E,)
        self._last_time_s = np.zeros(n_envs)  # (E,)
        self._window_start_s = np.full(n_envs, np.nan)  # (E,) first measured state; nan: none

    def _init_vehicles(self, n: int) -> None:
        self._n = n
        shape = (self.n_envs, n)
        self._is_cav = np.zeros(shape, dtype=bool)  # (E, V)
        self._seen = np.zeros(shape, dtype=bool)  # (E, V)
        self._waited = np.zeros(shape, dtype=bool)  # (E, V)
        self._sce = np.zeros(shape, dtype=bool)  # (E, V)
        self._arrived = np.zeros(shape, dtype=bool)  # (E, V)
        self._entered = np.zeros(shape, dtype=bool)  # (E, V) on the road at a recorded state
        self._first_time_s = np.full(shape, np.nan)  # (E, V)
        self._arrival_time_s = np.full(shape, np.nan)  # (E, V)
        self._window_time_s = np.full(shape, np.nan)  # (E, V) first measured on the road
        self._passed_before = np.zeros(shape, dtype=bool)  # (E, V) past the end at window start
        self._first_x_m = np.full(shape, np.nan)  # (E, V)
        self._last_x_m = np.full(shape, np.nan)  # (E, V)
        self._passed = np.zeros(shape, dtype=bool)  # (E, V) crossed the bottleneck's end

    def start(self, rows: np.ndarray) -> None:
        """Begin new episodes in ``rows`` (the others go on); their records are dropped."""
        rows = np.asarray(rows, np.int64)
        self._first_step[rows] = -1
        self._last_step[rows] = 0
        self._last_time_s[rows] = 0.0
        self._window_start_s[rows] = np.nan
        self._psar_counts[rows] = 0
        self._psar_decisions[rows] = 0
        for e in rows.tolist():
            self._collision_pairs[e] = []
        self._episode_chunk[rows] = self._chunk0 + len(self._chunks)
        dropped = int(self._episode_chunk.min()) - self._chunk0  # chunks no episode needs
        if dropped > 0:
            del self._chunks[:dropped]
            self._chunk0 += dropped
        if self._n is not None:
            for name in ("_is_cav", "_seen", "_waited", "_sce", "_arrived", "_entered"):
                getattr(self, name)[rows] = False
            for name in ("_passed_before", "_passed"):
                getattr(self, name)[rows] = False
            for name in ("_first_time_s", "_arrival_time_s", "_window_time_s"):
                getattr(self, name)[rows] = np.nan
            self._first_x_m[rows] = np.nan
            self._last_x_m[rows] = np.nan

    def record(
        self,
        state: TrafficState,
        psar: PSARResult | None = None,
        critical: np.ndarray | None = None,
        rows: np.ndarray | None = None,
    ) -> None:
        """Add one state (and the PSAR result of the step that led to it, if any).

        ``state`` is a batch of E envs (:mod:`diacc.sim.state`; one env is E = 1),
        ``psar`` its (E, C) PSAR result. ``critical``: (E, V) bool,
        ``safety_critical_events(state, events).any`` if the caller has it already.
        ``rows``: (E,) bool, the envs this state counts for (default all; a
        crashed simulator's row is left out).
        """
        if state.x_m.shape[0] != self.n_envs:
            raise MetricsError(f"state holds {state.x_m.shape[0]} envs, the recorder {self.n_envs}")
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
        kept = np.ones(self.n_envs, bool) if rows is None else np.asarray(rows, bool)  # (E,)
        time_s = np.asarray(state.time_s, np.float64)  # (E,)
        step = np.asarray(state.step, np.int64)  # (E,)
        first = kept & (self._first_step < 0)
        self._first_step[first] = step[first]
        self._is_cav[first] = state.is_cav[first]
        self._last_step[kept] = step[kept]
        active = state.active & kept[:, None]  # (E, V)
        self._first_time_s = np.where(active & ~self._entered, time_s[:, None], self._first_time_s)
        self._entered |= active
        self._last_time_s[kept] = time_s[kept]
        measured = kept & (time_s >= self.warmup_s - 1e-9)  # (E,)
        if not measured.any():
            return
        past_end = state.active & (state.x_m >= self._bottleneck_end_m)  # (E, V)
        opening = measured & np.isnan(self._window_start_s)  # first measured state: flows
        if opening.any():  # count from here
            self._window_start_s[opening] = time_s[opening]
            if self.warmup_s > 0:  # those passed during the warm-up
                self._passed_before[opening] = past_end[opening]

        on_road = state.active & measured[:, None]  # (E, V)
        env, idx = np.nonzero(on_road)  # (A,) each, env-major
        self._chunks.append(
            (
                env,
                idx.astype(np.int32),
                step[env].astype(np.int32),
                time_s[env],
                state.speed_mps[env, idx].astype(np.float64),
                self._kind_of_segment[state.segment[env, idx]],
                state.is_cav[env, idx],
            )
        )
        new = on_road & ~self._seen
        self._window_time_s = np.where(new, time_s[:, None], self._window_time_s)
        self._first_x_m = np.where(new, state.x_m, self._first_x_m)
        self._last_x_m = np.where(on_road, state.x_m, self._last_x_m)
        self._passed |= measured[:, None] & (state.arrived | past_end)
        self._seen |= on_road
        self._waited |= waiting_events(state, self.events) & measured[:, None]
        if critical is None:
            critical = safety_critical_events(state, self.events).any
        self._sce |= critical & measured[:, None]
        arrived = state.arrived & measured[:, None]
        self._arrival_time_s = np.where(
            arrived & ~self._arrived, time_s[:, None], self._arrival_time_s
        )
        self._arrived |= arrived
        collisions = state.collisions  # (K, 3) rows (env, i, j)
        if collisions.shape[0]:
            for e in np.unique(collisions[:, 0]).tolist():
                if measured[e]:
                    pairs = collisions[collisions[:, 0] == e, 1:]
                    self._collision_pairs[e].append(np.sort(pairs, axis=1))
        if psar is not None:
            counted = psar.active & measured[:, None]  # (E, C)
            bits = (psar.rule_mask[..., None].astype(np.int64) & RULE_BIT_VALUES) != 0
            self._psar_counts += (bits & counted[..., None]).sum(axis=1)
            self._psar_decisions += counted.sum(axis=1)

    def speed_samples(self, e: int = 0) -> SpeedSamples:
        """All speed samples of env ``e``'s episode (active vehicles), in recording order.

        Empty when every state so far lay in the warm-up: a demand episode that a
        collision ended before ``warmup_s`` still has its summary (measuring nothing).
        """
        if self._first_step[e] < 0:
            raise MetricsError("no state recorded yet")
        first = int(self._episode_chunk[e])
        chunks = self._chunks[first - self._chunk0 :]
        if not chunks:
            dtypes = (np.int32, np.int32, np.float64, np.float64, np.int8, bool)
            return SpeedSamples(*(np.zeros(0, dtype) for dtype in dtypes))
        # Envs whose episodes began together (every env of a batch, at once) share one
        # joined record until the next chunk: joined once, not once per env.
        key = (first, self._chunk0 + len(self._chunks))
        if self._joined_key != key:
            self._joined = [np.concatenate(c) for c in zip(*chunks, strict=True)]
            self._joined_key = key
        env, *cols = self._joined
        mine = env == e
        return SpeedSamples(*(col[mine] for col in cols))

    def summary(self, e: int = 0) -> EpisodeMetrics:
        """Reduce env ``e``'s records to :class:`EpisodeMetrics`."""
        samples = self.speed_samples(e)
        speed = samples.speed_mps
        seen, arrived_any = self._seen[e], self._arrived[e]  # (V,)
        n_seen = int(np.count_nonzero(seen))
        by_kind = {
            kind: _mean(speed[samples.segment_kind == k]) for k, kind in enumerate(SEGMENT_KINDS)
        }
        pairs = np.unique(
            np.concatenate([np.zeros((0, 2), np.int32), *self._collision_pairs[e]]), axis=0
        )
        n_collisions = int(pairs.shape[0])
        n_hdv_collisions = int(np.count_nonzero(~self._is_cav[e][pairs].any(axis=1)))
        first_time_s = self._first_time_s[e]
        travel_s = self._arrival_time_s[e] - first_time_s  # (V,) nan if not both
        travel_s[first_time_s < self.warmup_s - 1e-9] = np.nan  # entered in the warm-up
        decisions = int(self._psar_decisions[e])
        fire = {
            name: (float(count) / decisions if decisions else float("nan"))
            for name, count in zip(RULE_NAMES[1:], self._psar_counts[e].tolist(), strict=True)
        }
        arrived = arrived_any & seen  # (V,)
        return EpisodeMetrics(
            mean_speed_mps=_mean(speed),
            std_speed_mps=float(speed.std()) if speed.size else float("nan"),
            mean_cav_speed_mps=_mean(speed[samples.is_cav]),
            mean_hdv_speed_mps=_mean(speed[~samples.is_cav]),
            mean_speed_by_kind_mps=by_kind,
            p_we=_share(self._waited[e] & seen, n_seen),
            p_sce=_share(self._sce[e] & seen, n_seen),
            n_collisions=n_collisions,
            n_hdv_collisions=n_hdv_collisions,
            arrived_fraction=_share(arrived_any & seen, n_seen),
            mean_travel_time_s=_mean(travel_s[np.isfinite(travel_s)]),
            episode_steps=int(self._last_step[e] - max(self._first_step[e], 0)),
            n_vehicles=n_seen,
            psar_decisions=decisions,
            psar_fire_rate=fire,
            **self._flow(e, samples, arrived, n_seen),
        )

    def _flow(self, e: int, samples: SpeedSamples, arrived: np.ndarray, n_seen: int) -> dict:
        """The flow fields of :class:`EpisodeMetrics` (module docstring) of env ``e``."""
        window_start_s = float(self._window_start_s[e])
        last_time_s = float(self._last_time_s[e])
        duration_h = (last_time_s - (0.0 if np.isnan(window_start_s) else window_start_s)) / 3600.0
        seen = self._seen[e]  # (V,)
        n_passed = int(np.count_nonzero(self._passed[e] & seen & ~self._passed_before[e]))
        throughput = (
            n_passed / duration_h
            if duration_h > 0 and np.isfinite(self._bottleneck_end_m)
            else float("nan")
        )
        end_time_s = np.where(arrived, self._arrival_time_s[e], last_time_s)  # (V,)
        end_x_m = np.where(arrived, self._edges_m[-1], self._last_x_m[e])  # (V,)
        free_s = self._free_flow_s(end_x_m[seen]) - self._free_flow_s(self._first_x_m[e][seen])
        total_delay = float(np.sum(end_time_s[seen] - self._window_time_s[e][seen] - free_s))
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
