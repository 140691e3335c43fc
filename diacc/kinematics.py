"""Braking physics shared by PSAR and the simulators' lane-change rules.

A CAV acts once per decision step and holds its commanded speed change for
the whole step (:mod:`diacc.backends.base`). Whoever judges whether a gap in
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


def lane_change_reach_m(speed_mps: np.ndarray, step_s: float, length_m: np.ndarray) -> np.ndarray:
    """Road a vehicle needs ahead of its centre to complete a one-step lane change.

    The distance it covers during the step plus its own length; used with
    :meth:`diacc.maps.Map.lane_change_allowed` by PSAR and both backends.
    """
    return np.asarray(speed_mps) * step_s + np.asarray(length_m)
