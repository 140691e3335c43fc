"""Vectorised driver models of the highway backend: IDM, MOBIL, forced merge, boxes.

highway-env's ``IDMVehicle`` evaluates IDM and MOBIL one Python object at a
time (``highway_env/vehicle/behavior.py``), which is why the stock simulator
runs at ~10 steps/s with 25 vehicles. The functions here keep the *meaning*
of those models but evaluate every vehicle at once on (E, V) and (E, V, V)
arrays, one block per environment of a batch (V <= 60, so an all-pairs masked
matrix is cheaper than per-lane sorting in NumPy). Differences from the stock
models, each deliberate:

* IDM uses the bumper gap and a per-vehicle style (T, s0, a, b) instead of
  highway-env's class constants, and the standard ``max(0, .)`` on the
  dynamic part of the desired gap (Treiber's form).
* A lane that ends is seen by IDM as a standing obstacle at its end, and a
  vehicle in such a lane is *forced* to merge towards a continuing lane,
  with a gap-acceptance that relaxes as the lane end approaches. Stock MOBIL
  has neither, and deadlocks at lane drops (measured).
* Followers in the target lane of a waiting merger yield to it (treat it as
  their leader), so every merger eventually gets in.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from diacc.records import Batched
from diacc.sim.backends.highway.rows import per_vehicle, shared
from diacc.sim.state import flat_offsets


@dataclass(frozen=True)
class HighwayModel:
    """Constants of the highway backend's driver models (not user-facing config).

    Values follow highway-env where it has one (named in the comments) and
    are otherwise chosen so that pure-HDV traffic passes every shipped map.
    """

    max_brake_mps2: float = 9.0  # physical braking limit; IDM output is clipped here
    hdv_lane_change_s: float = 1.0  # duration of an HDV's lateral manoeuvre
    decision_period_s: float = 1.0  # how often HDVs reconsider lanes (highway-env: 1 s)
    lane_change_cooldown_s: float = 1.0  # highway-env LANE_CHANGE_DELAY
    mobil_max_imposed_brake_mps2: float = 2.0  # highway-env LANE_CHANGE_MAX_BRAKING_IMPOSED
    min_lane_change_speed_mps: float = 1.0  # highway-env: no discretionary change below 1 m/s
    merge_zone_m: float = 200.0  # forced merging starts this far before a lane end
    merge_lookahead_m: float = 100.0  # no discretionary change into a lane ending this close
    forced_max_imposed_brake_mps2: float = 6.0  # accepted follower braking right at the lane end
    min_accept_gap_m: float = 0.5  # smallest bumper gap a merger accepts front and rear
    yield_zone_m: float = 100.0  # followers start yielding when a merger is this close to its end
    yield_speed_mps: float = 2.0  # below this, even impolite drivers yield to the merger
    max_heading_rad: float = 0.35  # a car cannot crab sideways: heading is clipped here
    guard_gap_m: float = 0.1  # last-resort HDV-HDV spacing (counted in stats when used)

    @classmethod
    def of(cls, merges: str) -> HighwayModel:
        """The model of a ``SimConfig.highway_merges`` name (:data:`MERGE_MODELS`)."""
        return cls(**MERGE_MODELS[merges])


#: ``SimConfig.highway_merges`` -> the :class:`HighwayModel` constants it changes.
#:
#: * ``late`` (default; every committed highway result): forced merging from 200 m
#:   before a lane end, followers yield to a merger within 100 m of its end.
#: * ``early``: forced merging from 400 m, followers yield to a merger within 200 m of
#:   its end, and any follower slower than 8 m/s yields (not only polite ones). Merges
#:   spread upstream, as LC2013's strategic changes do on SUMO, so fewer drivers stand
#:   at the lane end and merge from rest: pure-HDV outflow in oversaturation rises to
#:   within 10 % of SUMO's (``diacc bench --fidelity --highway-merges early``; measured
#:   in benchmarks/studies/demand-human-traffic/results/). Starting merges early alone
#:   left single drivers standing minutes at the end; the earlier yielding lets them in.
MERGE_MODELS: dict[str, dict[str, float]] = {
    "late": {},
    "early": {"merge_zone_m": 400.0, "yield_zone_m": 200.0, "yield_speed_mps": 8.0},
}


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


@dataclass(frozen=True)
class IdmParams(Batched):
    """Per-vehicle IDM parameters, each (E, V): one row per environment of a batch.

    Nested in :class:`~.simstate.HighwayParams`, so it is a batched record whose
    fields declare their axes too (:mod:`.rows`). :meth:`take` builds other shapes
    (MOBIL's (E, 4, 3, V)) for a computation; those never go into a record.
    """

    headway_s: np.ndarray = per_vehicle()
    min_gap_m: np.ndarray = per_vehicle()
    accel_mps2: np.ndarray = per_vehicle()
    decel_mps2: np.ndarray = per_vehicle()
    delta: float = shared()  # IDM acceleration exponent

    def take(self, idx: np.ndarray) -> IdmParams:
        """Parameters of the vehicles ``idx`` (E, ...), each indexing its own env's row."""
        shape = self.headway_s.shape  # (E, V)
        flat = idx + flat_offsets(shape[:1], shape[1], idx.ndim - 1)

        def of(values: np.ndarray) -> np.ndarray:  # one flat take per parameter
            return np.ascontiguousarray(values).reshape(-1).take(flat)

        return IdmParams(
            of(self.headway_s),
            of(self.min_gap_m),
            of(self.accel_mps2),
            of(self.decel_mps2),
            self.delta,
        )


def idm_accel(
    speed_mps: np.ndarray,
    desired_mps: np.ndarray,
    params: IdmParams,
    gap_m: np.ndarray,
    lead_speed_mps: np.ndarray,
) -> np.ndarray:
    """IDM acceleration (unclipped); ``gap_m = inf`` means a free road.

    Same equation as ``IDMVehicle.acceleration``: a free-road term
    ``1 - (v / v0)^delta`` and an interaction term ``(s* / s)^2`` with
    ``s* = s0 + max(0, v T + v dv / (2 sqrt(a b)))``.
    """
    v = np.maximum(speed_mps, 0.0)
    free = 1.0 - np.power(v / np.maximum(desired_mps, 1e-3), params.delta)
    dynamic = v * params.headway_s + v * (v - lead_speed_mps) / (
        2.0 * np.sqrt(params.accel_mps2 * params.decel_mps2)
    )
    s_star = params.min_gap_m + np.maximum(dynamic, 0.0)
    interaction = np.square(s_star / np.maximum(gap_m, 1e-2))
    return params.accel_mps2 * (free - interaction)


def box_contacts(
    x_m: np.ndarray,
    y_m: np.ndarray,
    heading_rad: np.ndarray,
    length_m: float,
    width_m: float,
    active: np.ndarray,
) -> np.ndarray:
    """(E, V, V) bool, strictly upper triangular per env: oriented vehicle rectangles overlap.

    Inputs are (E, V), one row per environment; vehicles of different envs never
    meet. An axis-aligned bounding-box test over all pairs prunes, then the
    separating-axis theorem (4 axes per pair) decides the few candidates
    exactly, all vectorised.
    """
    cos_h, sin_h = np.cos(heading_rad), np.sin(heading_rad)  # (E, V)
    half_l, half_w = 0.5 * length_m, 0.5 * width_m
    ext_x = half_l * np.abs(cos_h) + half_w * np.abs(sin_h)  # (E, V)
    ext_y = half_l * np.abs(sin_h) + half_w * np.abs(cos_h)
    dx = x_m[:, None, :] - x_m[:, :, None]  # (E, V, V) x_j - x_i
    dy = y_m[:, None, :] - y_m[:, :, None]
    cand = (np.abs(dx) < ext_x[:, :, None] + ext_x[:, None, :]) & (
        np.abs(dy) < ext_y[:, :, None] + ext_y[:, None, :]
    )
    cand &= active[:, :, None] & active[:, None, :]
    cand = np.triu(cand, 1)
    if not cand.any():
        return cand
    e, i, j = np.nonzero(cand)  # (K,)
    # Axes: each box's long and lateral unit vectors -> (K, 4, 2).
    u_i = np.stack([cos_h[e, i], sin_h[e, i]], -1)
    n_i = np.stack([-sin_h[e, i], cos_h[e, i]], -1)
    u_j = np.stack([cos_h[e, j], sin_h[e, j]], -1)
    n_j = np.stack([-sin_h[e, j], cos_h[e, j]], -1)
    axes = np.stack([u_i, n_i, u_j, n_j], 1)
    centre = np.stack([dx[e, i, j], dy[e, i, j]], -1)[:, None, :]  # (K, 1, 2)

    def radius(u: np.ndarray, n: np.ndarray) -> np.ndarray:  # (K, 4)
        return half_l * np.abs((axes * u[:, None, :]).sum(-1)) + half_w * np.abs(
            (axes * n[:, None, :]).sum(-1)
        )

    separated = np.abs((axes * centre).sum(-1)) >= radius(u_i, n_i) + radius(u_j, n_j)
    overlap = ~separated.any(axis=1)  # (K,)
    out = np.zeros_like(cand)
    out[e[overlap], i[overlap], j[overlap]] = True
    return out
