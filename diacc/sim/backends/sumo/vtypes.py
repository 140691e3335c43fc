"""SUMO vehicle types (vTypes) from the shared driver styles and CAV limits.

Car-following models cannot be changed through TraCI, so the types are written
to an additional route file that the worker loads with the network. HDVs are
IDM + LC2013 with one vType per style of ``STYLE_PRESETS[sim.style_preset]``;
the CAV type depends on the CAV mode:

* ``commanded``: the policy drives. The CAV keeps SUMO's IDM only as a model
  of its physical limits; speeds come from ``slowDown`` with ``speedMode 0``
  (no built-in safety, as in the authors' environment) and lane changes from ``changeLane``.
* ``cooperative``: the non-learning "cooperative" baseline of the paper: CACC
  car following with ``lcCooperative = 1``, driving on its own with SUMO's
  default safety.

Every type uses ``speedFactor = 1`` without deviation: the desired speed is the
speed limit, as on the highway backend, so differences between backends come
from the driver models and not from a random speed distribution.
"""

from __future__ import annotations

import hashlib
from xml.sax.saxutils import quoteattr

from diacc.sim.drivers import STYLE_PRESETS
from diacc.sim.scenario import STYLE_NAMES
from diacc.sim.settings import SimConfig

#: vType id per style code (index = ``TrafficState.style``), CAVs use ``CAV_TYPE``.
HDV_TYPES = tuple(f"hdv_{name}" for name in STYLE_NAMES)
CAV_TYPE = "cav"


def vtypes_xml(sim: SimConfig) -> str:
    """Additional-file text with the three HDV types and the CAV type (``sim.cav_mode``)."""
    common = (
        f'length="{sim.vehicle_length_m}" width="{sim.vehicle_width_m}" '
        'speedFactor="1" speedDev="0" sigma="0" maxSpeed="70"'
    )
    rows = []
    for type_id, style in zip(HDV_TYPES, STYLE_PRESETS[sim.style_preset], strict=True):
        rows.append(
            f'    <vType id={quoteattr(type_id)} {common} carFollowModel="IDM" '
            f'delta="{sim.idm_delta}" tau="{style.time_headway_s}" minGap="{style.min_gap_m}" '
            f'accel="{style.accel_mps2}" decel="{style.decel_mps2}" '
            f'laneChangeModel="LC2013" lcCooperative="{style.lc_cooperative}" '
            f'lcSpeedGain="{style.lc_speed_gain}" lcStrategic="{style.lc_strategic}"'
            + (' lcCooperativeSpeed="1"' if style.zipper else "")
            + "/>"
        )
    cav = sim.cav
    if sim.cav_mode == "commanded":
        # The commanded CAV's own motion ignores its vType (speedMode 0, laneChangeMode 0):
        # decel, tau and minGap only tell the HDVs' LC2013 which gap a CAV needs behind
        # a vehicle cutting in; the lateral-speed terms let a lane change complete
        # within the step even from standstill, as on the highway backend.
        model = (
            f'carFollowModel="IDM" delta="{sim.idm_delta}" laneChangeModel="LC2013" '
            'lcMaxSpeedLatStanding="100" lcMaxSpeedLatFactor="100"'
        )
        decel_mps2, tau_s, min_gap_m = cav.safe_decel_mps2, *cut_in_gap_terms(sim)
    else:
        model = 'carFollowModel="CACC" laneChangeModel="LC2013" lcCooperative="1"'
        decel_mps2, tau_s, min_gap_m = cav.decel_mps2, cav.time_headway_s, cav.min_gap_m
    rows.append(
        f'    <vType id={quoteattr(CAV_TYPE)} {common} {model} tau="{tau_s}" '
        f'minGap="{min_gap_m}" accel="{cav.accel_mps2}" decel="{decel_mps2}" '
        f'emergencyDecel="{max(cav.decel_mps2, 9.0)}" color="0,160,255"/>'
    )
    return "<additional>\n" + "\n".join(rows) + "\n</additional>\n"


def cut_in_gap_terms(sim: SimConfig) -> tuple[float, float]:
    """The commanded CAV's ``tau`` and ``minGap``: what LC2013 asks of a gap in front of it.

    LC2013 lets an HDV cut in front of a CAV if the gap is at least
    ``minGap + v tau + (v^2 - v_l^2) / (2 b)`` at the CAV's *present* speed
    ``v``. But a commanded CAV may speed up by ``d = speed_change_mps`` over
    the step before it reacts: the highway backend asks the gap for that
    target speed (Gipps with one step ``T`` of reaction at ``v + d``,
    :mod:`diacc.sim.backends.highway.lanes`), which expands to
    ``min_gap + d T + d^2 / (2 b) + v (T + d / b) + (v^2 - v_l^2) / (2 b)``.
    So tau = T + d / b and minGap = min_gap + d T + d^2 / (2 b) make SUMO's
    HDVs leave the same gap. With tau = T alone they cut in front of CAVs that
    then accelerated and could not stop (issue 57: 1 in about 60 SUMO episodes
    at 4800 veh/h).
    """
    b, d, step_s = sim.cav.safe_decel_mps2, sim.speed_change_mps, sim.step_s
    return step_s + d / b, sim.cav.min_gap_m + d * step_s + d * d / (2.0 * b)


def vtypes_key(sim: SimConfig) -> str:
    """Short hash naming a vType file in the cache."""
    return hashlib.sha256(vtypes_xml(sim).encode()).hexdigest()[:16]
