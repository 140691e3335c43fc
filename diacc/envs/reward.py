"""Team reward of the paper (eq. reward_all .. reward_global) from a TrafficState.

``R = w_e * sum_i w_i r_e^i + w_g * r_g + r_done`` with softmin weights
``w_i = softmax(-r_e / tau)`` over the CAVs that are on the road. The pieces:

* ego reward of CAV ``i``::

      r_e = speed_weight * (-|v - v_max| / v_max + p_ev)
          + warning_weight * sum_{j: dist <= d_w} -(d_w - dist) / (d_w - d_c)
          + collision_weight * sum_{j in M_c} [-(d_c - dist)^+ / d_c + p_ec]
          + time_penalty_weight * (sigmoid(v - v_th) - 1)

  ``dist`` is the centre-to-centre distance to another active vehicle (HDV or
  CAV). The warning set holds every vehicle within ``d_w`` (the collision
  range included). The collision set ``M_c`` holds the vehicles within
  ``d_c`` *and* every vehicle the backend reported as colliding with ``i``
  this step: with 5 m long cars a real collision usually happens at a centre
  distance far above ``d_c`` = 1.5 m, and a collision must never go
  unpunished. For such a pair the distance part is clipped at 0, so it only
  contributes ``p_ec``.
* ``v_max`` of a CAV is the speed limit of the segment it is in (what the
  backend lets it reach; every shipped map has one limit, 25 m/s). The global
  term uses the mean of those limits over the active CAVs.
* ``r_g = -|mean v_CAV - v_max| / v_max + p_gv`` over active CAVs.
* ``r_done = exit_bonus`` for *each* CAV that arrived this step, not
  normalised by the number of CAVs (authors' "CAV exit bonus 20"); an episode
  in which all C CAVs leave thus earns ``C * exit_bonus`` in total. With
  ``crash_penalty > 0`` (an option; the paper's is 0) each CAV that collided
  this step adds ``-crash_penalty``: the trips that ended in the step, scored
  outside the softmin. Why: with per-CAV termination
  (``SimConfig.on_collision = "remove"``) a crash otherwise costs the team one
  step's collision term and the CAV's exit bonus, about what following a
  slower car costs over 20-30 steps, so crashing is no worse than braking
  (docs/results/nopsar-learning.md).
* With no CAV on the road the ego and global terms are 0 (nothing to score).

Options (:class:`~diacc.config.RewardConfig`; the defaults are the paper read
literally, docs/concepts/learning-options.md):

* ``closeness="bumper"``: ``dist`` is the bumper gap to the same-lane leader
  and follower (the gap of PSAR and the metrics) instead of the centre
  distance to everyone, and a closing leader with ``TTC <= warning_ttc_s``
  adds ``-(ttc_w - TTC) / ttc_w`` to the warning term.
* ``exit_bonus_scale="fleet"``: ``r_done = exit_bonus * arrivals / C``, so
  all CAVs leaving earn ``exit_bonus`` in total, not ``C`` times it.
* ``delay_weight > 0``: adds ``-delay_weight * sum_active (1 - v/v_lim)^+ / V``
  over *all* vehicles, the flow metrics' delay per second and vehicle.

**Two steps, one place.** :func:`reward_terms` scores a state: every part
that needs no temperature (the ego rewards ``r_e``, which CAVs are on the
road, ``r_g``, ``r_done`` and the delay term). :func:`team_reward` aggregates
them into ``R`` at a softmin temperature. Every environment emits ``R`` with
each step at the temperature it is *given* (its ``tau``; the vector envs of
training, :mod:`diacc.envs.vector`, and the PettingZoo env,
:class:`~diacc.envs.env.BottleneckEnv`) and counts nothing: the temperature
anneals over training (:func:`temperature`, paper eq. tau_annealing), and
only whoever trains knows how far training has got. ``diacc train`` sets it
before each rollout (:func:`diacc.learn.ppo.collect_rollout`); users of other
libraries wrap the PettingZoo env in :class:`~diacc.envs.env.AnnealTemperature`,
which sets it before each step. Either way they train on the same reward.

:func:`reward_terms` also scores a batch of E states ((E, V) arrays,
:mod:`diacc.sim.state`) in one call, and :func:`team_reward` takes any leading
env axis: every per-CAV array then has a leading env axis and every scalar is
an (E,) array; entry ``e`` is env ``e``'s reward.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from diacc.config import RewardConfig
from diacc.envs.safety import SAME_COL, lane_leaders_followers, pair_kinematics
from diacc.errors import DiaccError
from diacc.records import Batched, per_env
from diacc.sim.kinematics import nan_to_num
from diacc.sim.maps import Map
from diacc.sim.state import TrafficState, take, take_rows


class RewardError(DiaccError, ValueError):
    """Bad input to the reward (temperature <= 0, bad thresholds...); one line."""


def temperature(step: int, total_steps: int, cfg: RewardConfig) -> float:
    """Softmin temperature at a training step (paper eq. tau_annealing).

    Linear from ``tau_init`` to ``tau_final`` over the first
    ``tau_anneal_fraction * total_steps`` environment steps, then constant.
    ``total_steps`` is the run's budget, so that tau reaches ``tau_final`` at
    the same share of every run. Whoever trains applies it (module docstring).
    ``cfg``'s ranges (``tau_anneal_fraction`` in (0, 1], temperatures > 0) were
    checked when it was built (:class:`~diacc.config.RewardConfig`), so not here.
    """
    if total_steps <= 0:
        raise RewardError(f"total_steps must be positive, got {total_steps}")
    if step < 0:
        raise RewardError(f"step must be >= 0, got {step}")
    anneal_steps = cfg.tau_anneal_fraction * total_steps
    frac = min(step / anneal_steps, 1.0)
    return float(cfg.tau_init - (cfg.tau_init - cfg.tau_final) * frac)


def softmin_weights(ego_reward: np.ndarray, alive: np.ndarray, tau: float) -> np.ndarray:
    """Softmin weights ``exp(-r_i/tau) / sum_j exp(-r_j/tau)`` over alive agents.

    Computed with the max-shift trick so that tiny ``tau`` or large rewards do
    not overflow. Dead agents get weight 0; with no alive agent all are 0.

    Args:
        ego_reward: (..., C) ego rewards (values of dead agents are ignored).
        alive: (..., C) bool.
        tau: temperature > 0.

    Returns:
        (..., C) float64 weights summing to 1 over alive agents.
    """
    if not tau > 0.0:
        raise RewardError(f"softmin temperature must be > 0, got {tau}")
    alive = np.asarray(alive, dtype=bool)
    logits = np.where(alive, -np.asarray(ego_reward, dtype=np.float64) / tau, -np.inf)
    any_alive = alive.any(axis=-1, keepdims=True)  # (..., 1)
    shift = np.where(any_alive, logits.max(axis=-1, keepdims=True, initial=-np.inf), 0.0)
    expd = np.exp(logits - shift)  # (..., C), 0 for dead
    total = expd.sum(axis=-1, keepdims=True)
    return np.where(any_alive, expd / np.where(any_alive, total, 1.0), 0.0)


@dataclass
class RewardTerms(Batched):
    """The parts of one step's reward that need no temperature, one entry per CAV slot.

    Per-CAV arrays hold the *unweighted* sub-terms; ``ego`` is their weighted
    sum r_e. Entries of CAVs that are not on the road are 0. A batch of E envs
    (:class:`~diacc.records.Batched`: ``unbatched(e)`` is the PettingZoo env's view,
    (C,) arrays and floats). :func:`team_reward` makes the team reward R of them.
    """

    speed: np.ndarray = per_env("E, C")  # -|v - v_max|/v_max + p_ev
    warning: np.ndarray = per_env("E, C")  # warning-distance term (<= 0)
    collision: np.ndarray = per_env("E, C")  # collision term (<= 0)
    time_penalty: np.ndarray = per_env("E, C")  # sigmoid(v - v_th) - 1
    ego: np.ndarray = per_env("E, C")  # weighted ego reward r_e
    alive: np.ndarray = per_env("E, C")  # bool: on the road, or taken off by a crash in the step
    global_reward: np.ndarray = per_env("E")  # r_g
    completion: np.ndarray = per_env("E")  # r_done
    trip_end: np.ndarray = per_env("E, C")  # each slot's share of r_done: arrived or crashed
    delay: np.ndarray = per_env("E")  # minus the delay rate, before its weight delay_weight


@dataclass
class TeamReward(Batched):
    """The team reward R of a step at one softmin temperature (:func:`team_reward`); a
    batch as the terms are."""

    softmin_weight: np.ndarray = per_env("E, C")  # w_i, sums to 1 over alive CAVs
    ego_softmin: np.ndarray = per_env("E")  # sum_i w_i r_e^i
    total: np.ndarray = per_env("E")  # R


def team_reward(
    ego: np.ndarray,
    alive: np.ndarray,
    global_reward: float | np.ndarray,
    completion: float | np.ndarray,
    delay: float | np.ndarray,
    tau: float,
    cfg: RewardConfig,
) -> TeamReward:
    """Team reward ``R = w_e * sum_i w_i r_e^i + w_g * r_g + r_done + w_d * delay``.

    The softmin aggregation of the ego rewards at temperature ``tau`` and the
    weighted sum with the per-env terms, all of :class:`RewardTerms`
    (:func:`reward_terms`). Pure and vectorised: ``ego`` and ``alive`` are (C,)
    for one env or (..., C) for many, the other terms () or (...,).

    Args:
        ego: (..., C) ego rewards r_e (values of CAVs not on the road are ignored).
        alive: (..., C) bool, CAV on the road.
        global_reward: (...,) r_g.
        completion: (...,) r_done.
        delay: (...,) delay term before its weight.
        tau: softmin temperature > 0 (:func:`temperature`).
        cfg: the weights ``w_ego``, ``w_global`` and ``delay_weight``.

    Returns:
        :class:`TeamReward`, (...,) arrays (0-d for (C,) terms).
    """
    weights = softmin_weights(ego, alive, tau)  # (..., C)
    ego_softmin = np.sum(weights * ego, axis=-1)  # (...,)
    total = (
        cfg.w_ego * ego_softmin
        + cfg.w_global * global_reward
        + completion
        + cfg.delay_weight * delay
    )
    return TeamReward(
        softmin_weight=weights, ego_softmin=np.asarray(ego_softmin), total=np.asarray(total)
    )


def own_reward(terms: RewardTerms, cfg: RewardConfig) -> np.ndarray:
    """Each CAV's own reward ``w_e r_e^i + w_g r_g + r_done^i + w_d delay`` (E, C).

    Training's ``credit = "own"`` (:class:`~diacc.config.TrainConfig`): the
    team reward's terms without the softmin, each CAV credited with its own ego
    reward and its own trip's end (``trip_end``: its exit bonus, minus
    ``crash_penalty`` if it crashed); the global and delay terms stay shared.
    Why: with one team reward for ten CAVs a crash is charged to every CAV's
    actions alike (docs/results/nopsar-learning.md). 0 for slots not scored.
    """
    shared = cfg.w_global * terms.global_reward + cfg.delay_weight * terms.delay  # (E,)
    total = cfg.w_ego * terms.ego + np.asarray(shared)[..., None] + terms.trip_end  # (E, C)
    return np.where(terms.alive, total, 0.0)


def reward_terms(
    state: TrafficState,
    cav_index: np.ndarray,
    road: Map,
    cfg: RewardConfig,
) -> RewardTerms:
    """The reward parts of one step that need no temperature (see module docstring).

    Args:
        state: state *after* the step.
        cav_index: (..., C) vehicle indices of the CAV slots, ``...`` the state's leading
            (env) axes.
        road: the map (speed limits per segment).
        cfg: reward weights and thresholds (checked when it was built, e.g.
            ``collision_distance_m < warning_distance_m``; not on every call).

    Returns:
        :class:`RewardTerms`; :func:`team_reward` makes the team reward of them.
    """
    cav_index = np.asarray(cav_index)
    lead = state.x_m.shape[:-1]
    if (
        cav_index.ndim != len(lead) + 1
        or cav_index.shape[:-1] != lead
        or (cav_index.size and not np.issubdtype(cav_index.dtype, np.integer))
    ):
        raise RewardError(
            f"cav_index must be an integer array of shape (..., C) after the state's "
            f"leading axes {lead}, got shape {cav_index.shape}"
        )
    if np.any((cav_index < 0) | (cav_index >= state.n_vehicles)):
        raise RewardError(f"cav_index holds indices outside [0, {state.n_vehicles})")
    limits_mps = road.speed_limits_mps()  # (S,)
    if np.any(state.segment >= limits_mps.shape[0]):
        raise RewardError(f"segment index outside the map's {limits_mps.shape[0]} segments")

    # Scored: on the road after the step, or taken off it by a collision in the step
    # (SimConfig.on_collision = "remove"), whose penalty must count as when the
    # episode ends at the crash ("end"), where the wreck stays on the road.
    collided = state.collided  # (..., V) in a collision this step (built from the events)
    crashed = take(collided, cav_index)  # (..., C)
    alive = take(state.active, cav_index) | crashed  # (..., C)
    speed_mps = take(state.speed_mps, cav_index)  # (..., C)
    v_max_mps = limits_mps[take(state.segment, cav_index)]  # (..., C)

    # ---- distances to every other active vehicle ---------------------------
    dx_m = state.x_m[..., None, :] - take(state.x_m, cav_index)[..., None]  # (..., C, V)
    dy_m = state.y_m[..., None, :] - take(state.y_m, cav_index)[..., None]  # (..., C, V)
    dist_m = np.hypot(dx_m, dy_m)  # (..., C, V)
    not_self = np.arange(state.n_vehicles) != cav_index[..., None]  # (..., C, V)
    others = not_self & state.active[..., None, :]  # (..., C, V)
    collided_with = (
        take_rows(state.collided_with, cav_index)
        if len(state.collisions)
        else np.zeros(cav_index.shape + (state.n_vehicles,), bool)
    )  # (..., C, V)

    d_w, d_c = cfg.warning_distance_m, cfg.collision_distance_m
    if cfg.closeness == "bumper":
        dist_m, ttc_warning = _bumper_gaps(state, cav_index, others, cfg.warning_ttc_s)
    else:
        ttc_warning = 0.0
    in_warning = others & (dist_m <= d_w)  # (..., C, V)
    in_collision = (others & (dist_m <= d_c)) | (collided_with & not_self)  # (..., C, V)

    speed = -np.abs(speed_mps - v_max_mps) / v_max_mps + cfg.speed_offset
    warning = np.where(in_warning, -(d_w - dist_m) / (d_w - d_c), 0.0).sum(axis=-1)
    warning = warning + ttc_warning
    collision = np.where(
        in_collision, -np.maximum(d_c - dist_m, 0.0) / d_c + cfg.collision_offset, 0.0
    ).sum(axis=-1)
    time_penalty = 1.0 / (1.0 + np.exp(-(speed_mps - cfg.time_penalty_speed_mps))) - 1.0
    ego = (
        cfg.speed_weight * speed
        + cfg.warning_weight * warning
        + cfg.collision_weight * collision
        + cfg.time_penalty_weight * time_penalty
    )
    zero = np.zeros_like(ego)
    speed, warning, collision, time_penalty, ego = (
        np.where(alive, term, zero) for term in (speed, warning, collision, time_penalty, ego)
    )

    n_alive = alive.sum(axis=-1)
    any_alive = n_alive > 0
    safe_n = np.maximum(n_alive, 1)
    # Means over alive CAVs; with none alive, v_max_g = 1 keeps the unused branch finite.
    v_max_g = np.where(any_alive, np.where(alive, v_max_mps, 0.0).sum(axis=-1) / safe_n, 1.0)
    mean_speed_mps = np.where(alive, speed_mps, 0.0).sum(axis=-1) / safe_n
    global_reward = np.where(
        any_alive, -np.abs(mean_speed_mps - v_max_g) / v_max_g + cfg.global_offset, 0.0
    )
    n_cav_arrivals = (state.is_cav & state.arrived_now).sum(axis=-1)
    completion = cfg.exit_bonus * n_cav_arrivals
    if cfg.exit_bonus_scale == "fleet":
        completion = completion / max(cav_index.shape[-1], 1)
    # Each slot's part of r_done (the own-credit reward of training: own_reward).
    trip_end = cfg.exit_bonus * take(state.arrived_now, cav_index)  # (..., C)
    if cfg.exit_bonus_scale == "fleet":
        trip_end = trip_end / max(cav_index.shape[-1], 1)
    if cfg.crash_penalty:
        completion = completion - cfg.crash_penalty * (state.is_cav & collided).sum(axis=-1)
        trip_end = trip_end - cfg.crash_penalty * crashed
    delay = -_delay_rate(state, limits_mps)  # (...,) computed for the logs whatever the weight
    scalar = float if not lead else np.asarray
    return RewardTerms(
        speed=speed,
        warning=warning,
        collision=collision,
        time_penalty=time_penalty,
        ego=ego,
        alive=alive,
        global_reward=scalar(global_reward),
        completion=scalar(completion),
        trip_end=np.where(alive, trip_end, 0.0),
        delay=scalar(delay),
    )


def _bumper_gaps(
    state: TrafficState, cav_index: np.ndarray, others: np.ndarray, warning_ttc_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """Closeness by bumper gap and TTC (``RewardConfig.closeness = "bumper"``).

    Centre distance needs two 5 m cars to overlap before it drops to 3 m, so
    the paper's warning term never fires in lane-keeping traffic; the
    bumper gap to the same-lane leader and follower (:func:`pair_kinematics`,
    the gap PSAR and the metrics use) does. Returns a (..., C, V) "distance"
    table holding the bumper gap for those two vehicles and +inf for every
    other one, and the (..., C) TTC warning ``-(ttc_w - TTC) / ttc_w`` for a
    leader closing in with ``TTC <= ttc_w`` (0 otherwise), in [-1, 0].
    """
    lanes = lane_leaders_followers(state, cav_index)
    pair = np.stack([lanes.front[..., SAME_COL], lanes.rear[..., SAME_COL]], axis=-1)  # (..., C, 2)
    ego = np.broadcast_to(cav_index[..., None], pair.shape)
    kin = pair_kinematics(state, ego, pair)  # (..., C, 2)
    gap_m = np.where(kin.valid, np.abs(nan_to_num(kin.d_long_m)), np.inf)  # (..., C, 2)
    dist_m = np.full(others.shape, np.inf)  # (..., C, V)
    safe_pair = np.where(kin.valid, pair, 0)
    # One column at a time: a missing neighbour (index 0 after masking) keeps what is there.
    for col in (0, 1):
        current = np.take_along_axis(dist_m, safe_pair[..., col : col + 1], axis=-1)
        value = np.where(kin.valid[..., col : col + 1], gap_m[..., col : col + 1], current)
        np.put_along_axis(dist_m, safe_pair[..., col : col + 1], value, axis=-1)
    leader_ttc_s = kin.ttc_s[..., 0]  # (..., C), inf when not closing or no leader
    ttc_warning = np.where(
        leader_ttc_s <= warning_ttc_s, -(warning_ttc_s - leader_ttc_s) / warning_ttc_s, 0.0
    )
    return dist_m, ttc_warning


def _delay_rate(state: TrafficState, limits_mps: np.ndarray) -> np.ndarray:
    """(...,) seconds lost per second per vehicle: ``sum_active (1 - v / v_limit) / V``.

    The flow metrics' delay is vehicle-seconds lost against driving at each
    segment's limit, summed over all vehicles (HDVs included: what the CAVs
    change is the whole traffic's delay). Per step that is ``dt (1 - v/v_lim)``
    per active vehicle; per second and per vehicle of the scenario the term
    stays in [0, 1] whatever the demand, and driving above the limit earns
    nothing back (clipped at 0), so the term cannot pay for speeding.
    """
    v_limit_mps = limits_mps[np.minimum(np.maximum(state.segment, 0), limits_mps.shape[0] - 1)]
    lost = np.maximum(1.0 - state.speed_mps / v_limit_mps, 0.0)  # (..., V)
    return np.where(state.active, lost, 0.0).sum(axis=-1) / max(state.n_vehicles, 1)
