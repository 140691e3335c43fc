"""How a backend simulates: :class:`SimConfig` (steps, vehicle sizes, the driver
preset, how CAVs are driven) with the CAVs' physical limits (:class:`CavParams`),
and the backends' names.

The simulator's part of the config tree (``EnvConfig.sim``, :mod:`diacc.config`),
kept here so that the simulator never imports the config package; checked by the
same path as every section (:func:`diacc.fields.check_fields`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from diacc.fields import (
    MAX_EPISODE_STEPS,
    MAX_SUBSTEPS,
    ConfigError,
    check_fields,
    one_of,
    ranged,
)
from diacc.sim.drivers import STYLE_PRESETS

BACKENDS = ("highway", "sumo")
#: Backends whose simulator steps many envs as one batch (``vector = "batched"``; their
#: ``vector_mode``, :mod:`diacc.sim.backends`).
BATCHED_BACKENDS = ("highway",)
#: How CAVs are driven: by commands (learning and scripted policies) or on their
#: own as the non-learning ``cooperative`` baseline (CACC car following, lcCooperative 1).
CAV_MODES = ("commanded", "cooperative")
#: How the highway backend's human drivers leave an ending lane (``SimConfig.highway_merges``,
#: :data:`diacc.sim.backends.highway.models.MERGE_MODELS`): ``late`` (forced merging from
#: 200 m before the end) or ``early`` (from 400 m, with followers yielding sooner), which
#: passes SUMO's pure-HDV outflow in oversaturation within 10 % (docs/concepts/scenarios.md).
HIGHWAY_MERGES = ("late", "early")
#: What a collision does (``SimConfig.on_collision``): ``end`` the episode for every
#: vehicle (the paper's training episodes), or ``remove`` the vehicles that collided at
#: the end of the step (as SUMO's ``--collision.action remove``; they never arrive) and
#: run on to the horizon, so that an episode's delay and throughput are never those of
#: a shorter episode (evaluation's rule; docs/concepts/baselines.md, "Collisions").
ON_COLLISION = ("end", "remove")


def check_merges_backend(backend: str, highway_merges: str | None) -> None:
    """One-line :class:`ConfigError` if a merge model is asked of another backend than
    highway: SUMO's drivers merge by LC2013, so the option would be dropped unseen."""
    if highway_merges is not None and backend != "highway":
        raise ConfigError(
            f"--highway-merges {highway_merges} applies to the highway backend, not {backend} "
            "(SUMO's drivers merge by LC2013)"
        )


@dataclass(frozen=True)
class CavParams:
    """Physical limits of a CAV (SUMO vType of the authors) and its planned braking.

    ``decel_mps2`` is the physical limit the simulators enforce on commands.
    ``safe_decel_mps2`` is the braking the safety logic plans with: PSAR
    brakes at most this hard and sizes its safe gaps with it, and HDVs
    cutting in front of a CAV leave a gap it can brake for at this rate. It
    sits below the metrics' emergency-braking threshold
    (``EventConfig.emergency_decel_mps2``, 4.5) so that routine PSAR braking
    is not a safety-critical event, and below the limit so that a reserve is
    left.
    """

    time_headway_s: float = 1.0
    min_gap_m: float = 1.0
    accel_mps2: float = 5.0
    decel_mps2: float = 5.0
    safe_decel_mps2: float = 4.0

    def __post_init__(self) -> None:
        check_fields(self)
        if not 0.0 < self.safe_decel_mps2 <= self.decel_mps2:
            raise ConfigError(
                f"CAV safe_decel_mps2 must be in (0, decel_mps2 = {self.decel_mps2}], "
                f"got {self.safe_decel_mps2}"
            )


@dataclass(frozen=True)
class SimConfig:
    """How a backend simulates; shared by both backends, which trust it (checked here)."""

    step_s: float = ranged(1.0, 0, open_low=True)  # one decision step
    # highway backend integration steps per decision
    substeps: int = ranged(10, 1, MAX_SUBSTEPS, why="each is a pass over every vehicle")
    episode_steps: int = ranged(
        100, 1, MAX_EPISODE_STEPS, why="an episode's steps are stored and replayed in training"
    )
    speed_change_mps: float = ranged(2.0, 0)  # accelerate/decelerate action, over one step
    # decelerate lowers the target speed by speed_change_mps x this (1: the paper's +-2 m/s)
    decelerate_scale: float = ranged(1.0, 0, open_low=True)
    vehicle_length_m: float = ranged(5.0, 0, open_low=True)
    vehicle_width_m: float = ranged(1.8, 0, open_low=True)
    idm_delta: float = ranged(4.0, 0, open_low=True)  # IDM acceleration exponent
    style_preset: str = one_of("realistic", tuple(STYLE_PRESETS))  # diacc.sim.drivers
    cav_mode: str = one_of("commanded", CAV_MODES)
    # highway backend: how human drivers leave an ending lane (SUMO: LC2013's own lookahead)
    highway_merges: str = one_of("late", HIGHWAY_MERGES)
    on_collision: str = one_of("end", ON_COLLISION)
    cav: CavParams = field(default_factory=CavParams)

    def __post_init__(self) -> None:
        check_fields(self)
