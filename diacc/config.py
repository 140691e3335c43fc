"""Typed configuration. Defaults follow the DIACC paper and, where it is silent, the
authors' public predecessor environment (lzxphhh/HARL-based_simulator); the learner's
sizes are the measured cheaper ones (:class:`ModelConfig`; the paper's are
:data:`PAPER_LEARNER`, ``configs/paper-learner.toml``).

Configs are frozen dataclasses so that a run's settings cannot drift after
start-up; ``dataclasses.replace`` makes variants. :func:`override` applies a
flat ``{"section.field": value}`` mapping (from a TOML file or CLI flags) and
rejects unknown keys with a one-line :class:`ConfigError`. Each field's range
is written next to it (:func:`ranged`, :func:`one_of`) and checked once, when
any config is built (every float must also be finite), so code that reads a
config never checks it again; :func:`validate` adds the relations between
fields that a training run needs. :func:`build_train_config` is the
one place a :class:`TrainConfig` is assembled from user input (defaults < TOML
file < named options < ``--set`` pairs): ``diacc train``, ``diacc sweep`` and
``diacc reproduce`` all call it, so the library never goes through its own
command line.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from diacc.errors import DiaccError
from diacc.sim.maps import Map

# Style codes and mixes live with the scenario; re-exported here for convenience.
from diacc.sim.scenario import (  # noqa: F401
    AGGRESSIVE,
    CAUTIOUS,
    CAV_STYLE,
    MAX_VEHICLES,
    NORMAL,
    STYLE_MIXES,
    STYLE_NAMES,
    Scenario,
    ScenarioError,
)

# --------------------------------------------------------------------------
# Upper bounds of the size-like settings
# --------------------------------------------------------------------------
# Every count that sizes an array or a loop has an upper bound, so that a typo
# (``hidden_dim=1000000000``) is a one-line error before anything is allocated or
# written, not an allocator traceback or a hang. Each lies far above any setting
# the project uses and below what a 24 GiB, 2-core machine holds or finishes; the
# measurements behind them are in docs/guide/faults.md ("Size bounds").
#: Highway integration steps per decision: each one is a pass over every vehicle.
MAX_SUBSTEPS = 100
#: Decisions per episode (and per rollout, which holds whole episodes).
MAX_EPISODE_STEPS = 10_000
#: Observation neighbours K and history steps T: the actor's tables are (C, K, T).
MAX_NEIGHBOURS = 64
MAX_HISTORY_STEPS = 100
#: Width of any network layer: a 1024-wide learner already has ~44 M weights.
MAX_NETWORK_DIM = 1024
MAX_HEADS = 64
#: Environments of one run: every one adds a simulator and its rollout rows.
MAX_ENVS = 1024
#: PPO epochs over one rollout.
MAX_EPOCHS = 100
#: Bytes the rollout's observations may take (their upper estimate,
#: :func:`rollout_bytes`): a third of 24 GiB, as the update copies the batch again.
MAX_ROLLOUT_BYTES = 8 * 2**30


class ConfigError(DiaccError, ValueError):
    """An unknown or ill-typed configuration key; the message is one line."""


def _check_choice(key: str, value: str, choices: tuple[str, ...]) -> None:
    """One-line :class:`ConfigError` unless ``value`` is one of ``choices``."""
    if value not in choices:
        raise ConfigError(f"config key {key!r} must be one of {', '.join(choices)}, got {value!r}")


def ranged(
    default: Any, low: float, high: float | None = None, *, open_low: bool = False, why: str = ""
) -> Any:
    """A dataclass field whose value must lie in ``[low, high]`` (``(low, high]`` with
    ``open_low``; no upper bound when ``high`` is None).

    The range sits next to the field it bounds and is checked once, when the
    config is built (:func:`_check_fields` in each section's ``__post_init__``),
    so that no code reading the config checks it again. ``why`` says what the upper
    bound protects (memory, time); the error message ends with it.
    """
    return field(default=default, metadata={"range": (low, high, open_low), "why": why})


def one_of(default: str, choices: tuple[str, ...]) -> Any:
    """A dataclass field whose value must be one of ``choices`` (checked at construction)."""
    return field(default=default, metadata={"choices": choices})


class _FieldError(ConfigError):
    """A field's value out of its range; :func:`override` prefixes the section's path to
    ``key`` so the message names the dotted key the user typed."""

    def __init__(self, key: str, problem: str) -> None:
        super().__init__(f"config key {key!r} {problem}")
        self.key, self.problem = key, problem


def _check_fields(obj: Any, prefix: str = "") -> None:
    """Every float field finite, every :func:`ranged` field in range, every :func:`one_of`
    field one of its choices; one-line :class:`ConfigError` naming the first bad field.

    Nested sections check themselves; a tuple gives one value per item (``key[i]``).
    """
    for f in dataclasses.fields(obj):
        value, key = getattr(obj, f.name), f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            continue
        for item_key, item in (
            [(f"{key}[{i}]", v) for i, v in enumerate(value)]
            if isinstance(value, tuple)
            else [(key, value)]
        ):
            if isinstance(item, float) and not math.isfinite(item):
                raise _FieldError(item_key, f"must be a finite number, got {item}")
        if "range" in f.metadata:
            low, high, open_low = f.metadata["range"]
            too_low = value <= low if open_low else value < low
            if too_low or (high is not None and value > high):
                why = f" ({f.metadata['why']})" if f.metadata.get("why") and not too_low else ""
                raise _FieldError(
                    key, f"must be {_range_text(low, high, open_low)}, got {value}{why}"
                )
        if "choices" in f.metadata and value not in f.metadata["choices"]:
            choices = f.metadata["choices"]
            raise _FieldError(key, f"must be one of {', '.join(choices)}, got {value!r}")


def _range_text(low: float, high: float | None, open_low: bool) -> str:
    if high is None:
        return f"{'>' if open_low else '>='} {low}"
    return f"in {'(' if open_low else '['}{low}, {high}]"


# --------------------------------------------------------------------------
# Drivers
# --------------------------------------------------------------------------
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

    Applied wherever a run loads its map (environment, evaluator, ``simulate``),
    so backends, observations and the reward all see the same limits.
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
        if not 0.0 < self.safe_decel_mps2 <= self.decel_mps2:
            raise ConfigError(
                f"CAV safe_decel_mps2 must be in (0, decel_mps2 = {self.decel_mps2}], "
                f"got {self.safe_decel_mps2}"
            )
        _check_fields(self)


# --------------------------------------------------------------------------
# Simulation and scenario
# --------------------------------------------------------------------------
#: How CAVs are driven: by commands (learning and scripted policies) or on their
#: own as the non-learning ``cooperative`` baseline (CACC car following, lcCooperative 1).
CAV_MODES = ("commanded", "cooperative")


@dataclass(frozen=True)
class SimConfig:
    """How a backend simulates; shared by both backends, which trust it (checked here)."""

    step_s: float = 1.0  # one decision step
    # highway backend integration steps per decision
    substeps: int = ranged(10, 1, MAX_SUBSTEPS, why="each is a pass over every vehicle")
    episode_steps: int = ranged(
        100, 1, MAX_EPISODE_STEPS, why="an episode's steps are stored and replayed in training"
    )
    speed_change_mps: float = ranged(2.0, 0)  # accelerate/decelerate action, over one step
    vehicle_length_m: float = ranged(5.0, 0, open_low=True)
    vehicle_width_m: float = ranged(1.8, 0, open_low=True)
    idm_delta: float = ranged(4.0, 0, open_low=True)  # IDM acceleration exponent
    style_preset: str = "realistic"
    cav_mode: str = "commanded"  # or "cooperative" (see CAV_MODES)
    cav: CavParams = field(default_factory=CavParams)

    def __post_init__(self) -> None:
        _check_choice("sim.style_preset", self.style_preset, tuple(STYLE_PRESETS))
        _check_choice("sim.cav_mode", self.cav_mode, CAV_MODES)
        if not self.step_s > 0:
            raise ConfigError(f"SimConfig needs step_s > 0, got {self.step_s}")
        _check_fields(self)


# --------------------------------------------------------------------------
# Observation, safety, reward
# --------------------------------------------------------------------------
#: Values of ``ObservationConfig.lateral_frame`` (:mod:`diacc.envs.lateral_frame`).
LATERAL_FRAMES = ("drop-left", "world")


@dataclass(frozen=True)
class ObservationConfig:
    """Sizes of the observation layout (:mod:`diacc.envs.observation`) and three options.

    The options keep the layout (so every network and shipped checkpoint fits).
    ``lateral_frame = "drop-left"`` (default) shows a road that drops its right
    lanes mirrored, so agents trained on left drops know where the lanes end
    (:mod:`diacc.envs.lateral_frame`; the identity on every shipped map); ``"world"``
    is the literal reading. The two others default to the paper's observation.
    ``critic_step_input=False`` zeroes
    the critic's step / episode-length feature: with 100-step training and
    330-step evaluation episodes the value of a truncated episode otherwise
    extrapolates past anything seen. ``road_speed_limits=True`` writes each
    segment's speed limit / the route's highest into the road table's fourth
    column (otherwise 1 for every segment present), so actor and critic see
    the limits a preset lowers (``paper-congestion``).
    """

    # neighbour trajectories, current step included
    history_steps: int = ranged(5, 1, MAX_HISTORY_STEPS, why="actor tables are (C, K, T)")
    # nearest vehicles in same and adjacent lanes
    n_neighbours: int = ranged(6, 1, MAX_NEIGHBOURS, why="actor tables are (C, K, T)")
    # critic pads to this many vehicles (demand: on the road)
    max_vehicles: int = ranged(
        40, 1, MAX_VEHICLES, why="the critic pads to it; no scenario holds more vehicles"
    )
    lane_window_m: float = ranged(100.0, 0, open_low=True)  # lane statistics: ahead and behind
    critic_step_input: bool = True  # the critic's step / T feature (False: always 0)
    road_speed_limits: bool = False  # road table column 4 = segment limit / route max
    # "drop-left": a road dropping its right lanes is seen mirrored (diacc.envs.lateral_frame)
    lateral_frame: str = one_of("drop-left", LATERAL_FRAMES)

    def __post_init__(self) -> None:
        _check_fields(self)


#: Options of :class:`PSARConfig` (see :func:`diacc.envs.psar.psar`).
FORCE_BRAKE_MODES = ("cancel", "paper")
HORIZON_MODES = ("stopping", "headway", "paper")
#: When a CAV may brake beyond its planned rate under the ``"headway"`` horizon (PSARConfig).
FULL_BRAKE_MODES = ("bound", "threat", "known")


@dataclass(frozen=True)
class PSARConfig:
    """Thresholds of Algorithm 1 (the paper's and the authors' code's values) and two options.

    ``force_brake``: ``"cancel"`` brakes away the closing speed within the
    step (the authors' implementation, bounded by ``SimConfig.cav.decel_mps2``);
    ``"paper"`` is Algorithm 1 read literally (Force-Brake = action 4, one
    ``speed_change_mps`` step). ``horizon``: ``"headway"`` (the default) follows by
    braking physics alone (about 1 s behind an HDV, ``min_gap_m`` +
    ``cav_time_gap_s`` behind a CAV whose command is known;
    ``cooperative_merge``: CAVs open a gap for a CAV asking to merge);
    ``"stopping"`` (an earlier default, kept by every checkpoint and result made
    with it) lengthens the distance thresholds by a safe stopping
    gap, which keeps CAVs ~2.3 s behind HDVs; ``"paper"`` keeps them fixed.
    ``full_brake`` (``"headway"`` only): ``"threat"`` (an earlier
    default, kept by checkpoints made with it) brakes beyond the planned
    rate ``safe_decel_mps2`` only when a vehicle ahead brakes harder, is a CAV, is closer than
    ``min_gap_m`` or is so much slower that planned braking falls short, and
    restores a gap a cut-in shortened over several steps;
    ``"known"`` (the default, after ``"threat"``) is ``"threat"`` with a CAV leader
    judged by its known command of this step rather than always a threat;
    ``"bound"`` (before; kept by checkpoints made with it) brakes up to the
    physical limit whenever the speed bound asks (each cut-in then counts as an
    emergency brake in p(SCE)). ``coordinate_lane_changes`` stops two connected
    CAVs from changing lanes into each other. ``force_brake="paper", horizon="paper",
    coordinate_lane_changes=False`` is the literal pseudocode (the ablation);
    see :func:`diacc.envs.psar.psar`.
    """

    d_lc_min_m: float = 1.0
    d_safe_m: float = 5.0
    d_warn_m: float = 8.0
    d_att_m: float = 15.0
    ttc_safe_s: float = 2.0
    ttc_warn_s: float = 3.0
    ttc_att_s: float = 5.0
    b_max_mps2: float = 2.0
    force_brake: str = "cancel"
    horizon: str = "headway"
    coordinate_lane_changes: bool = True  # CAVs do not change lanes into each other
    queue_gap_m: float = 2.0  # standstill gap per vehicle queued at a lane end (PSAR's wall)
    min_gap_m: float = 2.0  # "headway": standstill gap kept behind any front obstacle
    cav_time_gap_s: float = 0.3  # "headway": time gap behind a CAV whose command is known
    cooperative_merge: bool = True  # "headway": CAVs open a gap for a CAV asking to merge in
    full_brake: str = "known"  # "headway": when to brake past the planned rate (FULL_BRAKE_MODES)

    def __post_init__(self) -> None:
        if not (self.d_lc_min_m <= self.d_safe_m < self.d_warn_m < self.d_att_m):
            raise ConfigError("PSARConfig needs d_lc_min_m <= d_safe_m < d_warn_m < d_att_m")
        if not (0 < self.ttc_safe_s < self.ttc_warn_s < self.ttc_att_s):
            raise ConfigError("PSARConfig needs 0 < ttc_safe_s < ttc_warn_s < ttc_att_s")
        if self.b_max_mps2 < 0:
            raise ConfigError(f"PSARConfig.b_max_mps2 must be >= 0, got {self.b_max_mps2}")
        _check_choice("psar.force_brake", self.force_brake, FORCE_BRAKE_MODES)
        _check_choice("psar.horizon", self.horizon, HORIZON_MODES)
        _check_choice("psar.full_brake", self.full_brake, FULL_BRAKE_MODES)
        if self.min_gap_m < 0 or self.cav_time_gap_s < 0:
            raise ConfigError(
                f"PSARConfig needs min_gap_m >= 0 and cav_time_gap_s >= 0, got "
                f"{self.min_gap_m} and {self.cav_time_gap_s}"
            )
        _check_fields(self)


@dataclass(frozen=True)
class EventConfig:
    """Thresholds of the metrics' event detectors."""

    waiting_speed_mps: float = 3.0
    sce_min_gap_m: float = 1.0
    sce_ttc_s: float = 1.5
    emergency_decel_mps2: float = 4.5

    def __post_init__(self) -> None:
        _check_fields(self)


#: Options of :class:`RewardConfig` (see :mod:`diacc.envs.reward`); the first is the paper's.
CLOSENESS_MODES = ("centre", "bumper")
EXIT_BONUS_SCALES = ("per_cav", "fleet")


@dataclass(frozen=True)
class RewardConfig:
    """Reward of paper eq. (reward_all..reward_global) with the authors' magnitudes.

    ``w_global`` is not derived from ``w_ego``: each is its own field. The paper
    ties them as w_g = 1 - w_e in its w_e-selection study (a larger w_e means
    "the reduced weight on the global reward"; its best w_e = 0.6 goes with
    the default w_g = 0.4), so ``--study w_e`` (:data:`diacc.experiments.sweepaxes.STUDIES`)
    moves both together; ``--sweep env.reward.w_ego=...`` alone keeps w_g.

    The last four fields are options that default to the paper's reading
    (:mod:`diacc.envs.reward`, docs/concepts/learning-options.md): ``closeness``,
    ``warning_ttc_s`` (used by ``closeness="bumper"``), ``exit_bonus_scale``
    and ``delay_weight``.
    """

    w_ego: float = ranged(0.6, 0)
    w_global: float = ranged(0.4, 0)
    speed_weight: float = 5.0  # speed term scaled to [0, 5]
    speed_offset: float = 1.0  # p_ev
    warning_distance_m: float = 3.0
    collision_distance_m: float = 1.5
    warning_weight: float = 0.5  # 0.05 x scale 10
    collision_weight: float = 1.0  # 0.05 x scale 20
    collision_offset: float = -10.0  # p_ec, fixed collision penalty
    time_penalty_weight: float = 1.0
    time_penalty_speed_mps: float = 5.0  # v_th
    global_offset: float = 1.0  # p_gv
    exit_bonus: float = 20.0  # r_done per CAV leaving the route
    tau_init: float = ranged(2.0, 0, open_low=True)
    tau_final: float = ranged(0.05, 0, open_low=True)
    tau_anneal_fraction: float = ranged(0.5, 0, 1, open_low=True)  # of the training steps
    # ---- options (diacc.envs.reward; docs/concepts/learning-options.md); defaults: the paper
    closeness: str = "centre"  # "centre" (paper) or "bumper": gap and TTC to lane leader/follower
    # "bumper": TTC to the same-lane leader that starts the warning
    warning_ttc_s: float = ranged(3.0, 0, open_low=True)
    exit_bonus_scale: str = "per_cav"  # "per_cav" (paper) or "fleet": bonus / CAV slots
    # weight of the delay term (vehicle-seconds lost / s / vehicle)
    delay_weight: float = ranged(0.0, 0)

    def __post_init__(self) -> None:
        _check_choice("env.reward.closeness", self.closeness, CLOSENESS_MODES)
        _check_choice("env.reward.exit_bonus_scale", self.exit_bonus_scale, EXIT_BONUS_SCALES)
        _check_fields(self)
        # the warning term divides by their difference (diacc.envs.reward)
        if not 0.0 < self.collision_distance_m < self.warning_distance_m:
            raise ConfigError(
                "RewardConfig needs 0 < collision_distance_m < warning_distance_m, got "
                f"{self.collision_distance_m} and {self.warning_distance_m}"
            )


BACKENDS = ("highway", "sumo")
#: Backends whose simulator steps many envs as one batch (``vector = "batched"``; their
#: ``vector_mode``, :mod:`diacc.sim.backends`).
BATCHED_BACKENDS = ("highway",)
#: How the actor's actions meet PSAR (:mod:`diacc.envs.action_mask`,
#: docs/concepts/learning-options.md): "proposed" trains on the proposed action (the paper read
#: literally), "executed" on the action PSAR executed, "masked" samples only
#: actions PSAR would execute unchanged.
PSAR_ACTION_MODES = ("proposed", "executed", "masked")


@dataclass(frozen=True)
class EnvConfig:
    """Everything that defines one environment; training nests one (``TrainConfig.env``)."""

    backend: str = "highway"
    map: str = "train-25"
    # None: on, or in a TrainConfig as its variant says (a value it contradicts is refused);
    # read it as psar_enabled
    use_psar: bool | None = None
    psar_actions: str = "proposed"  # PSAR_ACTION_MODES; not "proposed" needs use_psar
    scenario: Scenario = field(default_factory=Scenario)
    sim: SimConfig = field(default_factory=SimConfig)
    obs: ObservationConfig = field(default_factory=ObservationConfig)
    psar: PSARConfig = field(default_factory=PSARConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    events: EventConfig = field(default_factory=EventConfig)

    def __post_init__(self) -> None:
        _check_choice("backend", self.backend, BACKENDS)
        _check_choice("env.psar_actions", self.psar_actions, PSAR_ACTION_MODES)
        episode_s = self.sim.episode_steps * self.sim.step_s
        if self.scenario.warmup_s >= episode_s:
            raise ConfigError(
                f"scenario.warmup_s {self.scenario.warmup_s:g} s is not shorter than the episode "
                f"({self.sim.episode_steps} steps of {self.sim.step_s:g} s = {episode_s:g} s)"
            )
        _check_fields(self)
        # Scenario (diacc.sim.scenario) checks its own ranges; finiteness is checked here.
        _check_fields(self.scenario, "scenario.")

    @property
    def psar_enabled(self) -> bool:
        """Whether PSAR filters the CAVs' actions (``use_psar``, on when left unset)."""
        return self.use_psar is not False


# --------------------------------------------------------------------------
# Networks and training
# --------------------------------------------------------------------------
_DIM_WHY = "16x the paper's largest, 256; wider networks' updates take hours"
_HEADS_WHY = "each head is a full attention map"


@dataclass(frozen=True)
class ModelConfig:
    """Network sizes of actor and critic.

    The hidden sizes default to 64, the small end of the paper's "of the order
    64-256": with 4 minibatches (:class:`TrainConfig`) this learner learned at
    least as fast per environment step as 128 wide networks with 1 minibatch, at
    half the update cost (3 seeds x 32k steps, docs/benchmarks/index.md,
    ``benchmarks/studies/learner-settings/results/paper-vs-small-32k-3seeds``); every
    committed trained agent uses it. The paper's size is ``configs/paper-learner.toml``
    (:data:`PAPER_LEARNER`). A checkpoint keeps the sizes it was trained with.
    """

    hidden_dim: int = ranged(64, 1, MAX_NETWORK_DIM, why=_DIM_WHY)
    gat_heads: int = ranged(4, 1, MAX_HEADS, why=_HEADS_WHY)
    cross_heads: int = ranged(8, 1, MAX_HEADS, why=_HEADS_WHY)
    cross_dim: int = ranged(64, 1, MAX_NETWORK_DIM, why=_DIM_WHY)
    gru_hidden: int = ranged(64, 1, MAX_NETWORK_DIM, why=_DIM_WHY)
    leaky_slope: float = ranged(0.2, 0)
    taie_concat_heads: bool = False  # TAIE GAT heads hidden/heads wide, concatenated (cheaper)

    def __post_init__(self) -> None:
        _check_fields(self)


#: The paper-size learner (hidden sizes 128, one minibatch; entropy bonus 0.01: the
#: defaults before the small learner and the lower bonus) as config overrides;
#: ``configs/paper-learner.toml`` holds the same (a test keeps the two equal) and the
#: benchmarks compare against it.
PAPER_LEARNER: dict[str, Any] = {
    "model.hidden_dim": 128,
    "model.gru_hidden": 128,
    "minibatches": 1,
    "entropy_coef": 0.01,
}


@dataclass(frozen=True)
class Variant:
    """One row of the paper's ablation: which actor, which critic, PSAR on or off.

    Networks are named, not imported, so that configs stay free of torch;
    :mod:`diacc.learn.models.registry` maps the names to classes.
    """

    name: str
    actor: str  # "mlp" (plain MAPPO) or "diadm" (TAIE + GRU, the paper's D-IADM)
    critic: str  # "mlp" or "ciec" (ITDR + GRU, the paper's C-IEC)
    psar: bool  # actions pass through PSAR (paper: PSAR is part of D-IADM)


#: The variants, the only place they are defined: the paper's four, and plain MAPPO
#: under PSAR (``mappo-psar``, not in the paper), so that an ablation with PSAR on for
#: every row shows what the D-IADM actor and the C-IEC critic add.
VARIANT_TABLE: dict[str, Variant] = {
    v.name: v
    for v in (
        Variant("mappo", actor="mlp", critic="mlp", psar=False),
        Variant("mappo-iadm", actor="diadm", critic="mlp", psar=True),
        Variant("diacc-nopsar", actor="diadm", critic="ciec", psar=False),
        Variant("diacc", actor="diadm", critic="ciec", psar=True),
        Variant("mappo-psar", actor="mlp", critic="mlp", psar=True),
    )
}
VARIANTS = tuple(VARIANT_TABLE)
#: The paper's ablation (Table III): what ``diacc reproduce`` trains by default.
PAPER_VARIANTS = ("mappo", "mappo-iadm", "diacc-nopsar", "diacc")
#: How a checkpoint picks its evaluation actions: argmax, or drawn from its
#: distribution with a generator seeded by the episode (``--actions``).
ACTION_MODES = ("greedy", "sampled")


@dataclass(frozen=True)
class TrainConfig:
    """One training run: the variant, the PPO settings and the environment it trains in."""

    variant: str = "diacc"
    total_steps: int = ranged(3_000_000, 1)  # environment steps (decisions x envs)
    n_envs: int = ranged(20, 1, MAX_ENVS, why="each env adds a simulator and rollout rows")
    # sync (in process), batched (one highway simulator for all envs), process (worker
    # processes), auto (by backend: batched for highway, process for sumo)
    vector: str = one_of("auto", ("auto", "sync", "batched", "process"))
    rollout_steps: int = ranged(
        100, 1, MAX_EPISODE_STEPS, why="the rollout holds this many steps of every env"
    )
    seed: int = 1  # in [0, 2**32 - 1]
    # of the PPO update; rollout forwards always run on the CPU
    device: str = one_of("auto", ("auto", "cpu", "cuda"))
    # intra-op threads of the trainer; 0 = diacc.threads rule
    torch_threads: int = ranged(0, 0, 1024, why="more threads than cores only contend")
    update_bf16: bool = False  # bf16 autocast in the PPO update (changes numerics: option)
    update_compile: bool = False  # torch.compile the networks' sequence replay in the update
    # collect the next rollout while the learner trains (second thread): one-update policy lag
    overlap: bool = False
    lr: float = ranged(5e-4, 0, open_low=True)
    adam_eps: float = ranged(1e-5, 0, open_low=True)
    lr_decay: bool = True
    gamma: float = ranged(0.99, 0, 1)
    gae_lambda: float = ranged(0.95, 0, 1)
    clip: float = ranged(0.2, 0, open_low=True)
    epochs: int = ranged(5, 1, MAX_EPOCHS, why="each epoch replays the whole rollout")
    # of whole (chunk, env) sequences per epoch: 4 gives 20 Adam steps per update instead
    # of 5 at the same compute (ModelConfig: measured with hidden 64); needs
    # n_envs x rollout_steps / chunk_len >= minibatches (validate)
    minibatches: int = ranged(4, 1)
    # a tenth of the paper's 0.01 (kept by PAPER_LEARNER): with 0.01 sampled actions lost
    # to the heuristic (docs/results/learning-evidence.md, "Entropy bonus")
    entropy_coef: float = ranged(0.001, 0)
    value_coef: float = ranged(1.0, 0)
    huber_delta: float = ranged(10.0, 0, open_low=True)
    max_grad_norm: float = ranged(10.0, 0, open_low=True)
    chunk_len: int = ranged(10, 1)
    checkpoint_every: int = ranged(10, 1)  # updates
    # "team": one value per env, all CAVs share the advantage (paper); "per_agent":
    # a value per CAV slot from its own features beside the global state (docs)
    critic_values: str = one_of("team", ("team", "per_agent"))
    # maps trained on beside env.map: the envs are split into one near-equal share per
    # listed map (diacc.envs.vector.maps_of_envs), so one policy learns several road
    # layouts (--set extra_maps=train-25,right-50.toml); a map listed again gets another
    # share (extra_maps=train-50,train-25 with env.map train-50: 2/3 of the envs on it);
    # () trains on env.map alone
    extra_maps: tuple[str, ...] = ()
    # a checkpoint whose networks and value normaliser start this run (fine-tuning, e.g. a
    # highway-trained agent on SUMO: --init-from); the optimiser, the step count and the
    # lr and tau schedules start afresh. "" trains from random weights.
    init_from: str = ""
    run_dir: str = "runs/diacc"
    env: EnvConfig = field(default_factory=EnvConfig)
    model: ModelConfig = field(default_factory=ModelConfig)

    def __post_init__(self) -> None:
        _check_choice("variant", self.variant, VARIANTS)
        # The variant decides PSAR: an unset env.use_psar is derived from it, a given
        # one that contradicts it is refused (never overwritten).
        use_psar = VARIANT_TABLE[self.variant].psar
        if self.env.use_psar is None:
            object.__setattr__(self, "env", dataclasses.replace(self.env, use_psar=use_psar))
        elif self.env.use_psar != use_psar:
            wanted = self.env.use_psar
            others = [v.name for v in VARIANT_TABLE.values() if v.psar == wanted]
            raise ConfigError(
                f"env.use_psar={str(wanted).lower()} contradicts variant {self.variant!r}, "
                f"which {'uses' if use_psar else 'does not use'} PSAR; the variant "
                f"decides it: choose one {'with' if wanted else 'without'} PSAR "
                f"({', '.join(others)})"
            )
        _check_fields(self)
        if not 0 <= self.seed < 2**32:
            raise ConfigError(f"seed must be in [0, 2**32 - 1], got {self.seed}")


def override(config: Any, values: dict[str, Any]) -> Any:
    """Return a copy of a (nested) config dataclass with dotted keys replaced.

    ``override(TrainConfig(), {"lr": 1e-3, "reward.w_ego": 0.8})``. Unknown
    keys and values of the wrong type raise :class:`ConfigError`. Each section
    is rebuilt once with all its new values, so the checks in its
    ``__post_init__`` see them together (``psar.d_warn_m`` and
    ``psar.d_att_m`` can move in one call).
    """
    tree: dict[str, Any] = {}
    for key, value in values.items():
        *parents, leaf = key.split(".")
        node = tree
        for name in parents:
            node = node.setdefault(name, {})
            if not isinstance(node, dict):
                raise ConfigError(f"unknown config key {key!r}")
        node[leaf] = value
    return _replace(config, tree, "")


def _replace(obj: Any, tree: dict[str, Any], prefix: str) -> Any:
    names = {f.name for f in dataclasses.fields(obj)}
    changes = {}
    for key, value in tree.items():
        head, full_key = key.replace("-", "_"), f"{prefix}{key}"
        if head not in names:
            raise ConfigError(f"unknown config key {full_key!r}")
        current = getattr(obj, head)
        if dataclasses.is_dataclass(current) and isinstance(value, dict):
            changes[head] = _replace(current, value, f"{full_key}.")
        elif isinstance(value, dict):
            raise ConfigError(f"unknown config key {full_key + '.' + next(iter(value), '')!r}")
        elif dataclasses.is_dataclass(current) and not isinstance(value, type(current)):
            raise ConfigError(
                f"config key {full_key!r} is a section; set its fields ({full_key}.NAME=VALUE)"
            )
        else:
            changes[head] = _coerce(_unset_as(obj, head, current), value, full_key)
    if isinstance(obj, TrainConfig) and "variant" in changes and _rederive_psar(tree):
        # a new variant derives env.use_psar again (the old one derived the current value)
        changes["env"] = dataclasses.replace(changes.get("env", obj.env), use_psar=None)
    try:
        if isinstance(obj, Scenario):  # derives a demand's count again
            return obj.replace(**changes)
        return dataclasses.replace(obj, **changes)
    except _FieldError as exc:  # a field of this section: name it by its full key
        raise _FieldError(f"{prefix}{exc.key}", exc.problem) from None
    except ScenarioError as exc:  # Scenario checks itself (diacc.sim.scenario): name its key
        raise ScenarioError(f"{prefix.rstrip('.')}: {exc}") from None


def _unset_as(obj: Any, name: str, current: Any) -> Any:
    """A value of the type a field ``X | None`` takes when it is None (unset), so that
    :func:`_coerce` parses a given value by it (``--set env.use_psar=false``)."""
    if current is not None:
        return current
    hint = next(f.type for f in dataclasses.fields(obj) if f.name == name)
    kind = str(hint).split("|")[0].strip()
    return {"bool": False, "int": 0, "float": 0.0, "str": ""}.get(kind, current)


def _rederive_psar(tree: dict[str, Any]) -> bool:
    """Whether an override tree leaves ``env.use_psar`` to the variant: it sets neither
    that field nor a whole ``env`` section (an EnvConfig, which says its own)."""
    env = next((v for k, v in tree.items() if k.replace("-", "_") == "env"), {})
    return isinstance(env, dict) and all(k.replace("-", "_") != "use_psar" for k in env)


def _coerce(current: Any, value: Any, key: str) -> Any:
    kind = type(current)
    if kind is tuple:  # of strings: "a,b" (--set) or a TOML / JSON list
        items = value.split(",") if isinstance(value, str) else value
        if not isinstance(items, list | tuple) or not all(isinstance(v, str) for v in items):
            raise ConfigError(f"config key {key!r} expects a list of names, got {value!r}")
        return tuple(v.strip() for v in items if v.strip())
    if isinstance(value, str) and kind is not str:
        try:
            if kind is bool:
                if value.lower() not in ("true", "false", "1", "0"):
                    raise ValueError
                return value.lower() in ("true", "1")
            return kind(value)
        except ValueError:
            raise ConfigError(
                f"config key {key!r} expects {kind.__name__}, got {value!r}"
            ) from None
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise ConfigError(f"config key {key!r} expects {kind.__name__}, got {value!r}")
    return value


def build_train_config(
    file: str | Path | None = None,
    *,
    variant: str | None = None,
    backend: str | None = None,
    map: str | None = None,  # noqa: A002 - the option's name
    steps: int | None = None,
    envs: int | None = None,
    seed: int | None = None,
    device: str | None = None,
    run_dir: str | Path | None = None,
    style_preset: str | None = None,
    init_from: str | Path | None = None,
    sets: Iterable[str] | Mapping[str, Any] = (),
) -> TrainConfig:
    """The training config of user input: defaults < TOML ``file`` < named options < ``sets``.

    One function for every entry point (``diacc train``, ``sweep``, ``reproduce``)
    so that they resolve settings the same way and the library never builds a
    command line to call itself. A named option left at None keeps the file's
    (or the default) value; ``steps`` is ``total_steps`` (environment steps,
    decisions x environments), ``envs`` is ``n_envs``, ``style_preset`` is
    ``env.sim.style_preset``, ``init_from`` the checkpoint a fine-tuning run starts
    from. ``sets`` are ``KEY=VALUE`` texts (``--set``) or a
    mapping of dotted keys to values. All layers are applied in one
    :func:`override`, so a value one layer asks for and the variant contradicts
    (``env.use_psar``) is refused, whichever layer named the variant. Without a
    ``run_dir`` anywhere the run goes to ``runs/<variant>-<backend>-<map>-s<seed>``
    of the resolved config. Not validated here (:func:`validate` runs before a
    run writes anything); bad keys and values raise a one-line :class:`ConfigError`.
    """
    from diacc.tomlfile import read_toml

    values: dict[str, Any] = {}
    if file is not None:
        if not Path(file).exists():
            raise ConfigError(f"config file {file} does not exist")
        values.update(_flatten(read_toml(Path(file), ConfigError)))
    named = {
        "variant": variant,
        "env.backend": backend,
        "env.map": None if map is None else str(map),
        "total_steps": steps,
        "n_envs": envs,
        "seed": seed,
        "device": device,
        "run_dir": None if run_dir is None else str(run_dir),
        "env.sim.style_preset": style_preset,
        "init_from": None if init_from is None else str(init_from),
    }
    values.update({k: v for k, v in named.items() if v is not None})
    values.update(sets if isinstance(sets, Mapping) else parse_sets(sets))
    cfg = override(TrainConfig(), values)
    if not any(key.replace("-", "_") == "run_dir" for key in values):
        cfg = dataclasses.replace(cfg, run_dir=default_run_dir(cfg))
    return cfg


def default_run_dir(cfg: TrainConfig) -> str:
    """``runs/<variant>-<backend>-<map>-s<seed>``: where a run goes that names no directory."""
    from diacc.sim.maps import map_tag

    return f"runs/{cfg.variant}-{cfg.env.backend}-{map_tag(cfg.env.map)}-s{cfg.seed}"


def parse_sets(items: Iterable[str]) -> dict[str, str]:
    """``["KEY=VALUE", ...]`` (``--set``) -> ``{KEY: VALUE}``; the values stay text for
    :func:`override` to parse by the field's type (a later KEY wins)."""
    values: dict[str, str] = {}
    for item in items:
        if "=" not in item:
            raise ConfigError(f"--set expects KEY=VALUE, got {item!r}")
        key, value = item.split("=", 1)
        values[key] = value
    return values


def _flatten(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested TOML tables -> dotted keys (``{"env": {"map": m}}`` -> ``{"env.map": m}``)."""
    out: dict[str, Any] = {}
    for key, value in tree.items():
        if isinstance(value, Mapping) and value:  # an empty one stays for override to judge
            out.update(_flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


# --------------------------------------------------------------------------
# Stored configs (checkpoints, config.json)
# --------------------------------------------------------------------------
#: Version of the config schema a checkpoint stores (its ``config_schema``; a config
#: without one is version 1). Raise it whenever a field moves or its default changes,
#: and add the step that rewrites a stored config of the version before into the new
#: one to :data:`_MIGRATIONS`, so that loading never switches how a trained policy
#: was run (docs/concepts/conventions.md, "Configuration").
CONFIG_SCHEMA = 2

#: Sections a TrainConfig held at its top level before it nested an EnvConfig.
_ENV_SECTIONS_BEFORE_NESTING = ("backend", "map", "sim", "scenario", "obs", "psar", "reward")
#: Defaults of version 1 that version 2 changed; a version-1 config without the field
#: meant these: ``env.psar.horizon`` ("stopping"), ``env.psar.full_brake`` ("bound"),
#: the learner's sizes, minibatches and entropy bonus (:data:`PAPER_LEARNER`).
_SCHEMA_1_DEFAULTS = {
    "env.psar.horizon": "stopping",
    "env.psar.full_brake": "bound",
    **PAPER_LEARNER,
}


def _schema_1_to_2(flat: dict[str, Any]) -> dict[str, Any]:
    """Version 1 -> 2 of a flat stored config: the environment's sections move under
    ``env`` (configs that predate the nesting), a missing field takes its version-1
    default."""
    if not any(key.split(".")[0] == "env" for key in flat):
        flat = {
            f"env.{key}" if key.split(".")[0] in _ENV_SECTIONS_BEFORE_NESTING else key: value
            for key, value in flat.items()
        }
    return {**_SCHEMA_1_DEFAULTS, **flat}


#: version -> the step that rewrites a stored config of that version (flat: dotted keys)
#: into the next.
_MIGRATIONS = {1: _schema_1_to_2}


def stored_config(stored: dict[str, Any], schema: Any = 1) -> TrainConfig:
    """The TrainConfig a stored config of ``schema`` means (one-line ConfigError if none).

    Migrated step by step to :data:`CONFIG_SCHEMA`; a field it lacks then takes its
    current default. Values pass the same checks (ranges, bounds, contradictions) as
    any user input.
    """
    if not isinstance(schema, int) or isinstance(schema, bool) or schema < 1:
        raise ConfigError(f"config schema must be a positive integer, got {schema!r}")
    if schema > CONFIG_SCHEMA:
        raise ConfigError(
            f"config schema {schema} is newer than this diacc's ({CONFIG_SCHEMA}); update diacc"
        )
    flat = flatten_config(stored)
    for version in range(schema, CONFIG_SCHEMA):
        flat = _MIGRATIONS[version](flat)
    return override(TrainConfig(), flat)


def flatten_config(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (lists as tuples), the keys :func:`override` takes."""
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            flat.update(flatten_config(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = tuple(value) if isinstance(value, list) else value
    return flat


# --------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------
def rollout_bytes(cfg: TrainConfig) -> int:
    """Upper estimate of the bytes a rollout's observations take (the memory bound of
    :func:`validate`), without building anything.

    Counts every value of :mod:`diacc.envs.observation`'s layout as 8 bytes and a
    node as 8 features (the layout has 6), so that it stays above the real size
    (``ObservationSpec.actor_shapes`` / ``critic_shapes``; a test keeps it so):
    per CAV slot its own and K neighbours' (HDV and CAV) T-step histories, masks and
    lane and road tables; per env the critic's ``max_vehicles`` rows.
    """
    obs, scenario = cfg.env.obs, cfg.env.scenario
    k, t = obs.n_neighbours, obs.history_steps
    per_slot = (2 * k + 1) * t * 8 + 3 * k + 64
    per_env = obs.max_vehicles * (2 * k + 8) + 16
    per_step = max(1, scenario.n_slots) * per_slot + per_env
    return 8 * cfg.rollout_steps * cfg.n_envs * per_step


def validate(cfg: TrainConfig) -> TrainConfig:
    """Reject settings that cannot train together (one-line ConfigError).

    Each field's own range, finiteness and choices are checked when the config
    is built (:func:`ranged`, :func:`one_of`, the sections' ``__post_init__``);
    what is left are relations between fields that only a training run needs.
    Called before a run writes anything, so a bad value never leaves a run
    directory behind or surfaces later as a NaN checkpoint or a torch error.
    """
    if rollout_bytes(cfg) > MAX_ROLLOUT_BYTES:
        raise ConfigError(
            f"the rollout's observations would take about {rollout_bytes(cfg) / 2**30:.3g} GiB "
            f"(rollout_steps {cfg.rollout_steps} x n_envs {cfg.n_envs} x "
            f"{cfg.env.scenario.n_slots} CAV slots, env.obs n_neighbours "
            f"{cfg.env.obs.n_neighbours}, history_steps {cfg.env.obs.history_steps}, "
            f"max_vehicles {cfg.env.obs.max_vehicles}); at most "
            f"{MAX_ROLLOUT_BYTES / 2**30:g} GiB, a third of a 24 GiB machine"
        )
    if cfg.env.scenario.n_cavs < 1:
        raise ConfigError(
            f"env.scenario: {cfg.env.scenario.n_vehicles} vehicles at cav_penetration "
            f"{cfg.env.scenario.cav_penetration} make 0 CAVs; training needs at least one"
        )
    if cfg.total_steps < cfg.rollout_steps * cfg.n_envs:
        # An update collects rollout_steps x n_envs steps: a smaller budget would
        # run one update far past it.
        raise ConfigError(
            f"total_steps {cfg.total_steps} is less than one update "
            f"(rollout_steps {cfg.rollout_steps} x n_envs {cfg.n_envs} = "
            f"{cfg.rollout_steps * cfg.n_envs} steps)"
        )
    if cfg.vector == "batched" and cfg.env.backend not in BATCHED_BACKENDS:
        raise ConfigError(
            f"vector 'batched' steps every env in one simulator, which backend "
            f"{cfg.env.backend!r} does not have ({', '.join(BATCHED_BACKENDS)} does); "
            "use vector auto, sync or process"
        )
    if cfg.env.psar_actions != "proposed" and not cfg.env.use_psar:
        raise ConfigError(
            f"env.psar_actions {cfg.env.psar_actions!r} needs PSAR, which variant "
            f"{cfg.variant!r} does not use"
        )
    if cfg.init_from and not Path(cfg.init_from).is_file():
        raise ConfigError(f"init_from: checkpoint {cfg.init_from} does not exist")
    if cfg.rollout_steps % cfg.chunk_len:
        raise ConfigError(
            f"rollout_steps {cfg.rollout_steps} must be a multiple of chunk_len {cfg.chunk_len}"
        )
    if cfg.rollout_steps < cfg.env.sim.episode_steps:
        # Every update restarts the environments: a shorter rollout would never
        # reach (nor train on) the ends of episodes.
        raise ConfigError(
            f"rollout_steps {cfg.rollout_steps} must be >= env.sim.episode_steps "
            f"{cfg.env.sim.episode_steps}, so that rollouts hold whole episodes"
        )
    maps = (cfg.env.map, *cfg.extra_maps)
    if len(maps) > cfg.n_envs:
        raise ConfigError(
            f"{len(maps)} training maps ({', '.join(maps)}) need at least as many envs, "
            f"got n_envs {cfg.n_envs}"
        )
    sequences = cfg.n_envs * (cfg.rollout_steps // cfg.chunk_len)
    if cfg.minibatches > sequences:
        # A minibatch is at least one whole (chunk, env) sequence.
        raise ConfigError(
            f"minibatches {cfg.minibatches} exceeds the rollout's {sequences} sequences "
            f"(n_envs {cfg.n_envs} x rollout_steps {cfg.rollout_steps} / chunk_len "
            f"{cfg.chunk_len}); set minibatches <= {sequences} or raise n_envs or rollout_steps"
        )
    return cfg


def _leaves(obj: Any, prefix: str = "") -> list[tuple[str, Any]]:
    """(dotted key, value) of every non-dataclass field; tuples give one leaf per item."""
    out = []
    for f in dataclasses.fields(obj):
        value, key = getattr(obj, f.name), f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            out += _leaves(value, f"{key}.")
        elif isinstance(value, tuple):
            out += [(f"{key}[{i}]", v) for i, v in enumerate(value)]
        else:
            out.append((key, value))
    return out
