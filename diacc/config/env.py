"""The environment's settings: :class:`EnvConfig` and its sections (observation,
PSAR, reward, event thresholds), with the simulator's (:class:`SimConfig`) and the
traffic's (:class:`~diacc.sim.scenario.Scenario`) nested in it, and the road it
describes (:func:`resolve_road`)."""

from __future__ import annotations

from dataclasses import dataclass, field

from diacc.fields import (
    MAX_HISTORY_STEPS,
    MAX_NEIGHBOURS,
    MAX_VEHICLES,
    ConfigError,
    check_fields,
    one_of,
    ranged,
)
from diacc.sim.drivers import preset_road
from diacc.sim.maps import Map, load_map
from diacc.sim.scenario import Scenario
from diacc.sim.settings import BACKENDS, SimConfig

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
        check_fields(self)


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
    b_max_mps2: float = ranged(2.0, 0)
    force_brake: str = one_of("cancel", FORCE_BRAKE_MODES)
    horizon: str = one_of("headway", HORIZON_MODES)
    coordinate_lane_changes: bool = True  # CAVs do not change lanes into each other
    queue_gap_m: float = 2.0  # standstill gap per vehicle queued at a lane end (PSAR's wall)
    min_gap_m: float = ranged(2.0, 0)  # "headway": standstill gap kept behind any front obstacle
    cav_time_gap_s: float = ranged(
        0.3, 0
    )  # "headway": time gap behind a CAV whose command is known
    cooperative_merge: bool = True  # "headway": CAVs open a gap for a CAV asking to merge in
    # "headway": when to brake past the planned rate
    full_brake: str = one_of("known", FULL_BRAKE_MODES)

    def __post_init__(self) -> None:
        check_fields(self)
        if not (self.d_lc_min_m <= self.d_safe_m < self.d_warn_m < self.d_att_m):
            raise ConfigError("PSARConfig needs d_lc_min_m <= d_safe_m < d_warn_m < d_att_m")
        if not (0 < self.ttc_safe_s < self.ttc_warn_s < self.ttc_att_s):
            raise ConfigError("PSARConfig needs 0 < ttc_safe_s < ttc_warn_s < ttc_att_s")


@dataclass(frozen=True)
class EventConfig:
    """Thresholds of the metrics' event detectors."""

    waiting_speed_mps: float = 3.0
    sce_min_gap_m: float = 1.0
    sce_ttc_s: float = 1.5
    emergency_decel_mps2: float = 4.5

    def __post_init__(self) -> None:
        check_fields(self)


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

    ``crash_penalty`` and the last four fields are options that default to the
    paper's reading (:mod:`diacc.envs.reward`, docs/concepts/learning-options.md):
    ``closeness``, ``warning_ttc_s`` (used by ``closeness="bumper"``),
    ``exit_bonus_scale`` and ``delay_weight``.
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
    # r_done per CAV crashing: minus this (0, the paper: its crash costs the collision term only)
    crash_penalty: float = ranged(0.0, 0)
    tau_init: float = ranged(2.0, 0, open_low=True)
    tau_final: float = ranged(0.05, 0, open_low=True)
    tau_anneal_fraction: float = ranged(0.5, 0, 1, open_low=True)  # of the training steps
    # ---- options (diacc.envs.reward; docs/concepts/learning-options.md); defaults: the paper
    # "centre" (paper) or "bumper": gap and TTC to lane leader/follower
    closeness: str = one_of("centre", CLOSENESS_MODES)
    # "bumper": TTC to the same-lane leader that starts the warning
    warning_ttc_s: float = ranged(3.0, 0, open_low=True)
    # "per_cav" (paper) or "fleet": bonus / CAV slots
    exit_bonus_scale: str = one_of("per_cav", EXIT_BONUS_SCALES)
    # weight of the delay term (vehicle-seconds lost / s / vehicle)
    delay_weight: float = ranged(0.0, 0)

    def __post_init__(self) -> None:
        check_fields(self)
        # the warning term divides by their difference (diacc.envs.reward)
        if not 0.0 < self.collision_distance_m < self.warning_distance_m:
            raise ConfigError(
                "RewardConfig needs 0 < collision_distance_m < warning_distance_m, got "
                f"{self.collision_distance_m} and {self.warning_distance_m}"
            )


#: How the actor's actions meet PSAR (:mod:`diacc.envs.action_mask`,
#: docs/concepts/learning-options.md): "proposed" trains on the proposed action (the paper read
#: literally), "executed" on the action PSAR executed, "masked" samples only
#: actions PSAR would execute unchanged.
PSAR_ACTION_MODES = ("proposed", "executed", "masked")


@dataclass(frozen=True)
class EnvConfig:
    """Everything that defines one environment; training nests one (``TrainConfig.env``)."""

    backend: str = one_of("highway", BACKENDS)
    map: str = "train-25"
    # None: on, or in a TrainConfig as its variant says (a value it contradicts is refused);
    # read it as psar_enabled
    use_psar: bool | None = None
    # not "proposed" needs PSAR (validate)
    psar_actions: str = one_of("proposed", PSAR_ACTION_MODES)
    scenario: Scenario = field(default_factory=Scenario)
    sim: SimConfig = field(default_factory=SimConfig)
    obs: ObservationConfig = field(default_factory=ObservationConfig)
    psar: PSARConfig = field(default_factory=PSARConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    events: EventConfig = field(default_factory=EventConfig)

    def __post_init__(self) -> None:
        check_fields(self)
        episode_s = self.sim.episode_steps * self.sim.step_s
        if self.scenario.warmup_s >= episode_s:
            raise ConfigError(
                f"scenario.warmup_s {self.scenario.warmup_s:g} s is not shorter than the episode "
                f"({self.sim.episode_steps} steps of {self.sim.step_s:g} s = {episode_s:g} s)"
            )

    @property
    def psar_enabled(self) -> bool:
        """Whether PSAR filters the CAVs' actions (``use_psar``, on when left unset)."""
        return self.use_psar is not False


def resolve_road(config: EnvConfig) -> Map:
    """The road ``config`` drives on: its map (a shipped name or a ``.toml`` path) with
    its style preset's speed limits (:func:`~diacc.sim.drivers.preset_road`).

    The one place a map name becomes a road, so that backends, observations, reward
    and the trainer's checks all see the same limits; a layer that holds a road
    (a backend's ``road``) passes it on rather than resolving the name again.
    """
    return preset_road(load_map(config.map), config.sim.style_preset)
