"""Human driving styles and the named presets that set them, for both simulators.

A :class:`DriverStyle` is one style's IDM and lane-change terms; a preset
(:data:`STYLE_PRESETS`, chosen by ``SimConfig.style_preset``) gives the three
styles of the paper's mixes (aggressive, normal, cautious) and may lower the
reduction segments' speed limit (:func:`preset_road`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from diacc.sim.maps import Map


@dataclass(frozen=True)
class DriverStyle:
    """One human driving style, described once for both simulators.

    The IDM terms mean the same on both backends (SUMO vType ``tau``,
    ``minGap``, ``accel``, ``decel``). Lane changing is LC2013 on SUMO and
    MOBIL on highway: ``politeness`` and ``lc_gain_threshold_mps2`` are the
    MOBIL image of LC2013's ``lcCooperative`` and ``lcSpeedGain``.
    """

    name: str
    time_headway_s: float  # IDM T / SUMO tau
    min_gap_m: float  # IDM s0 / SUMO minGap
    accel_mps2: float  # IDM a
    decel_mps2: float  # IDM b (comfortable braking)
    politeness: float  # MOBIL p in [0, 1]
    lc_gain_threshold_mps2: float  # MOBIL delta_a_th
    lc_cooperative: float  # SUMO LC2013 lcCooperative
    lc_speed_gain: float  # SUMO LC2013 lcSpeedGain
    lc_strategic: float  # SUMO LC2013 lcStrategic
    #: Lets a vehicle waiting at a lane end in, braking harder than comfortable if
    #: need be (SUMO lcCooperativeSpeed 1; highway: yields up to the forced-merge
    #: braking). Off in the paper's presets; the ``zipper`` preset turns it on.
    zipper: bool = False
    #: highway: forced merging starts this far before a lane end (None: the model's
    #: 200 m); the highway image of a small lcStrategic (a driver who merges late).
    merge_zone_m: float | None = None


_AGGRESSIVE = DriverStyle("aggressive", 0.9, 1.0, 3.5, 5.5, 0.0, 0.05, 0.0, 100.0, 100.0)
_NORMAL = DriverStyle("normal", 1.0, 1.5, 2.5, 4.5, 0.5, 0.2, 0.5, 1.0, 0.5)
#: The authors' cautious values: lcStrategic -1 means "never change lanes because
#: the route needs it", so a cautious driver in an ending lane stops at its end
#: and stays there (both backends; the highway backend skips its forced merge).
_CAUTIOUS_PAPER = DriverStyle("cautious", 1.2, 2.0, 1.5, 2.5, 1.0, 0.6, -1.0, 0.0, -1.0)
#: Named style presets (the authors' cautious lcStrategic -1 strands drivers at lane
#: ends; docs/benchmarks/index.md "Congestion presets" has the measured pure-HDV
#: rows of each):
#:
#: * ``realistic`` (default): every driver merges (cautious lcStrategic 0.2).
#: * ``zipper``: ``realistic``, and every driver lets one waiting at a lane end in.
#: * ``paper``: the authors' cautious values; cautious drivers in an ending lane
#:   get stuck at its end, as in the paper's pure-HDV row.
#: * ``paper-congestion``: ``paper`` with normal drivers' lcStrategic at SUMO's
#:   default 1.0 (the paper: "normal driving adopts default SUMO model
#:   parameters") and the reduction segments' speed limit lowered to
#:   :data:`PRESET_REDUCTION_SPEED_MPS` (:func:`preset_road`). With 330-step
#:   episodes it gives the paper's pure-HDV congestion.
#: * ``merge-congestion``: congestion made by merging, without stuck drivers:
#:   ``paper-congestion``'s normal drivers and 15 m/s reduction segments, and
#:   cautious drivers who keep the paper's car following but merge late
#:   (lcStrategic 0.05 on SUMO, forced merging from 30 m before the lane end
#:   on highway) and reluctantly (lcCooperative 0, high MOBIL threshold).
#:   Every driver leaves an ending lane; the queue forms at the drop.
STYLE_PRESETS: dict[str, tuple[DriverStyle, DriverStyle, DriverStyle]] = {
    "paper": (_AGGRESSIVE, _NORMAL, _CAUTIOUS_PAPER),
    "paper-congestion": (
        _AGGRESSIVE,
        dataclasses.replace(_NORMAL, lc_strategic=1.0),
        _CAUTIOUS_PAPER,
    ),
    "realistic": (
        _AGGRESSIVE,
        _NORMAL,
        DriverStyle("cautious", 1.2, 2.0, 1.5, 2.5, 1.0, 0.6, 0.0, 0.0, 0.2),
    ),
    "merge-congestion": (
        _AGGRESSIVE,
        dataclasses.replace(_NORMAL, lc_strategic=1.0),
        DriverStyle("cautious", 1.2, 2.0, 1.5, 2.5, 1.0, 0.6, 0.0, 0.0, 0.05, merge_zone_m=30.0),
    ),
}
#: ``zipper``: ``realistic`` drivers who also let a driver waiting at a lane end in
#: (:attr:`DriverStyle.zipper`): without it a cautious driver who reached the end
#: of an ending lane can stand there over a minute beside a 22 m/s stream (measured
#: on the demand scenario, docs/concepts/scenarios.md).
STYLE_PRESETS["zipper"] = tuple(
    dataclasses.replace(style, zipper=True) for style in STYLE_PRESETS["realistic"]
)


#: Speed limit of the reduction segments per preset (presets not listed keep the
#: map's). 15 m/s is the limit of the authors' predecessor bottleneck
#: (lzxphhh/HARL-based_simulator); the paper gives the route's *maximum* limit
#: only (25 m/s).
PRESET_REDUCTION_SPEED_MPS: dict[str, float] = {"paper-congestion": 15.0, "merge-congestion": 15.0}


def preset_road(road: Map, style_preset: str) -> Map:
    """The road a preset drives on: ``road`` with its reduction segments' speed
    limit replaced where :data:`PRESET_REDUCTION_SPEED_MPS` names one.

    Applied where an environment's map becomes its road
    (:func:`diacc.config.resolve_road`), so backends, observations and the reward
    all see the same limits.
    """
    limit = PRESET_REDUCTION_SPEED_MPS.get(style_preset)
    if limit is None:
        return road
    segments = tuple(
        dataclasses.replace(seg, speed_limit_mps=min(seg.speed_limit_mps, limit))
        if seg.kind.startswith("reduction")
        else seg
        for seg in road.segments
    )
    return dataclasses.replace(road, segments=segments)
