"""Braking physics shared by PSAR and the simulators' lane-change rules.

A CAV acts once per decision step and holds its commanded speed change for
the whole step (:mod:`diacc.sim.backends.base`). Whoever judges whether a gap in
front of a CAV is safe -- PSAR deciding when to brake, or an HDV deciding
whether it may cut in -- must therefore allow for one step of *reaction*
and then for braking at the CAV's deceleration limit while the vehicle ahead
may brake just as hard. Both use the one formula here (Gipps' safe gap), so
a gap the simulator lets an HDV take is a gap PSAR can brake for.
"""

from __future__ import annotations

import numpy as np


def safe_gap_m(
    speed_mps: np.ndarray | float,
    lead_speed_mps: np.ndarray | float,
    reaction_s: np.ndarray | float,
    decel_mps2: float,
    end_speed_mps: np.ndarray | float | None = None,
) -> np.ndarray:
    """Bumper gap a follower needs to stop behind a leader that brakes as hard as it can.

    ``(v + v_T) / 2 * T + (v_T^2 - v_l^2) / (2 b)``, at least 0 (Gipps 1981):
    the follower (speed ``v``) reaches ``v_T = end_speed_mps`` (default: keeps
    ``v``) during the reaction time ``T`` and then brakes at ``b``; the leader
    (``v_l``) brakes at ``b`` at once. A standing obstacle (``v_l = 0``) gives
    the full stopping distance; equal, steady speeds give the reaction
    distance ``v T``.
    """
    v = np.maximum(np.asarray(speed_mps, dtype=np.float64), 0.0)
    v_end = v if end_speed_mps is None else np.maximum(np.asarray(end_speed_mps), 0.0)
    v_lead = np.maximum(np.asarray(lead_speed_mps, dtype=np.float64), 0.0)
    reaction_m = 0.5 * (v + v_end) * reaction_s
    return np.maximum(reaction_m + (v_end * v_end - v_lead * v_lead) / (2.0 * decel_mps2), 0.0)


#: The largest float64, what :func:`numpy.nan_to_num` makes of an infinity.
_FLOAT_MAX = np.finfo(np.float64).max


def nan_to_num(values: np.ndarray) -> np.ndarray:
    """:func:`numpy.nan_to_num` of float64 values (NaN -> 0, +-inf -> the largest
    floats), bit for bit, at less than half its cost: PSAR calls it every step."""
    values = np.asarray(values, dtype=np.float64)
    clipped = np.minimum(np.maximum(values, -_FLOAT_MAX), _FLOAT_MAX)
    return np.where(np.isnan(values), 0.0, clipped)


def lane_change_reach_m(speed_mps: np.ndarray, step_s: float, length_m: np.ndarray) -> np.ndarray:
    """Road a vehicle needs ahead of its centre to complete a one-step lane change.

    The distance it covers during the step plus its own length; used with
    :meth:`diacc.sim.maps.Map.lane_change_allowed` by PSAR and both backends.
    """
    return np.asarray(speed_mps) * step_s + np.asarray(length_m)


def safe_end_speed_mps(
    gap_m: np.ndarray,
    speed_mps: np.ndarray,
    lead_step_m: np.ndarray,
    lead_end_speed_mps: np.ndarray,
    step_s: float,
    decel_mps2: np.ndarray | float,
    min_gap_m: float | np.ndarray,
    time_gap_s: float | np.ndarray = 0.0,
    lead_decel_mps2: np.ndarray | float | None = None,
) -> np.ndarray:
    """Highest speed a follower may command for the end of a step and still stop in time.

    The follower ramps linearly from ``v = speed_mps`` to ``u`` over the step
    (how both backends execute a command), while the leader covers
    ``lead_step_m`` and ends at ``w = lead_end_speed_mps``; from then on the
    follower can brake at ``b = decel_mps2`` (it decides again at the next
    step) and the leader may brake at ``b_l = lead_decel_mps2`` (default ``b``).
    The largest ``u`` with

        gap + lead_step - (v + u) T / 2 >= min_gap + time_gap * u
                                            + max(0, u^2 / (2 min(b, b_l)) - w^2 / (2 b_l))

    is returned (it can be negative: then no command keeps the gap). The
    braking term compares stopping points; with ``min(b, b_l)`` it also holds
    when the follower brakes harder than the leader (then the closest point
    is not at the stop, so the follower is credited only the leader's rate).
    For a leader whose command is unknown, pass its worst case
    (:func:`braking_step`): with equal decelerations the result equals
    Gipps' :func:`safe_gap_m` with one step of reaction. The left side falls
    and the right side grows with ``u``, so the root is unique; it is found
    in closed form on each side of the point where the braking term starts.
    """
    v = np.maximum(np.asarray(speed_mps, dtype=np.float64), 0.0)
    w = np.maximum(np.asarray(lead_end_speed_mps, dtype=np.float64), 0.0)
    # Scalars stay Python floats (the same values, without numpy's cost per 0-d operation:
    # PSAR evaluates this a dozen times per step).
    b_eff = b_lead = _float_or_array(decel_mps2)
    u0 = w  # the braking term is 0 up to here: w sqrt(b_eff / b_lead), and b_eff = b_lead
    if lead_decel_mps2 is not None:
        b_lead = _float_or_array(lead_decel_mps2)
        b_eff = np.minimum(b_eff, b_lead)
        u0 = w * np.sqrt(b_eff / b_lead)
    slope = 0.5 * step_s + _float_or_array(time_gap_s)  # d(need)/du below u0
    room_m = np.asarray(gap_m) + np.asarray(lead_step_m) - 0.5 * v * step_s - min_gap_m
    below_mps = room_m / slope  # root if it lies at or below u0
    # Above u0: u^2 / (2 b_eff) + slope u - (room + w^2 / (2 b_lead)) = 0.
    c = room_m + w * w / (2.0 * b_lead)
    with np.errstate(invalid="ignore"):
        above_mps = b_eff * (-slope + np.sqrt(slope * slope + 2.0 * c / b_eff))
    # No root (NaN) is -inf; infinities become the largest floats (as np.nan_to_num does).
    above_mps = np.minimum(np.maximum(above_mps, -_FLOAT_MAX), _FLOAT_MAX)
    return np.where(below_mps <= u0, below_mps, np.where(np.isnan(above_mps), -np.inf, above_mps))


def _float_or_array(value: np.ndarray | float) -> np.ndarray | float:
    """A scalar as a Python float, anything else as a float64 array."""
    if isinstance(value, (float, int)):  # a setting (np.float64 is a float)
        return float(value)
    return np.asarray(value, dtype=np.float64)


def braking_step(
    speed_mps: np.ndarray, step_s: float, decel_mps2: np.ndarray | float
) -> tuple[np.ndarray, np.ndarray]:
    """(distance m, end speed m/s) of a vehicle braking at ``decel_mps2`` for one step.

    The worst case PSAR assumes for a leader whose command it does not know.
    """
    v = np.maximum(np.asarray(speed_mps, dtype=np.float64), 0.0)
    end_mps = np.maximum(v - decel_mps2 * step_s, 0.0)
    return (v * v - end_mps * end_mps) / (2.0 * decel_mps2), end_mps
