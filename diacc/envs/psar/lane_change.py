"""Algorithm 1's lane-change checks (lines 2-16), and the road's and connected CAVs' own.

In order: a change the road does not allow becomes ``remain`` before
Algorithm 1 (:func:`refuse_impossible`); the target lane's front obstacle
cancels or slows the change (Cancel-LC, Decel-LC); its rear vehicle, or a
vehicle behind already moving across into it, cancels it; and two connected
CAVs do not change into each other's way (:func:`clashes`). The distances are
Algorithm 1's plus the horizon's margins (:mod:`diacc.envs.psar.horizons`).
"""

from __future__ import annotations

import numpy as np

from diacc.config import PSARConfig, SimConfig
from diacc.envs.actions import (
    ACTION_LANE_OFFSET,
    LANE_LEFT,
    LANE_RIGHT,
    REMAIN,
    lane_change_allowed,
)
from diacc.envs.psar.result import CANCEL_LC, DECEL_LC, rule_bit
from diacc.envs.psar.scene import Cavs, Margins, Obstacles
from diacc.envs.safety import PairKinematics
from diacc.sim.kinematics import nan_to_num
from diacc.sim.maps import Map
from diacc.sim.state import take


def refuse_impossible(
    cavs: Cavs, proposed: np.ndarray, road: Map, sim: SimConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A lane change the road does not allow (:func:`~diacc.envs.actions.lane_change_allowed`)
    -> ``remain``, so the car-following checks still run (else a policy could dodge them
    by asking for an impossible change). Returns (..., C) each: the actions, the
    refused changes, the changes left."""
    a = proposed.copy()
    is_lc = cavs.active & ((a == LANE_LEFT) | (a == LANE_RIGHT))
    invalid_lc = is_lc & ~lane_change_allowed(cavs.state, cavs.index, a, road, sim)
    a = np.where(invalid_lc, REMAIN, a)
    return a, invalid_lc, is_lc & ~invalid_lc


def check_lane_changes(
    cavs: Cavs,
    a: np.ndarray,
    is_lc: np.ndarray,
    near: Obstacles,
    horizon: Margins,
    cfg: PSARConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lines 2-16 on the lane changes ``is_lc`` of actions ``a`` (..., C).

    Returns (..., C) each: the actions (cancelled changes -> ``remain``), Decel-LC's
    braking ``b_lc`` (m/s^2, 0 where none or cancelled) and the rule mask.
    """
    cancel_front, b_lc_mps2 = _check_front(cavs, a, is_lc, near, horizon, cfg)
    still_lc = is_lc & ~cancel_front
    cancel_rear = _check_rear(still_lc, near.tr_vehicle, near.tr_index, b_lc_mps2, horizon, cfg)
    # A vehicle behind whose change into the target lane is under way is one of its rear
    # vehicles already, though its centre is not there yet (scene.joining_target).
    cancel_rear |= _check_rear(
        still_lc, near.joining_rear, near.joining_rear_index, b_lc_mps2, horizon, cfg
    )
    cancel = cancel_front | cancel_rear
    clash = clashes(cavs, ACTION_LANE_OFFSET[a], still_lc & ~cancel_rear, horizon, cfg)
    cancel |= clash & cfg.coordinate_lane_changes
    a = np.where(cancel, REMAIN, a)
    b_lc_mps2 = np.where(cancel, 0.0, b_lc_mps2)
    mask = np.zeros(cavs.shape, dtype=np.int8)
    mask |= rule_bit(cancel, CANCEL_LC)
    mask |= rule_bit(b_lc_mps2 > 0.0, DECEL_LC)
    return a, b_lc_mps2, mask


def _check_front(
    cavs: Cavs,
    a: np.ndarray,
    is_lc: np.ndarray,
    near: Obstacles,
    horizon: Margins,
    cfg: PSARConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """Cancel-LC and Decel-LC against the target lane's front vehicle and its end (a
    standing obstacle, :func:`~diacc.envs.safety.lane_end_kinematics`).

    Decel-LC: ``b_lc = min(|dv_long|, b_max)`` with the front obstacle, applied over
    the step of the change; zeroed if the change is cancelled. Returns (..., C) each:
    cancelled, ``b_lc``.
    """
    cancel_front = np.zeros(cavs.shape, dtype=bool)
    b_lc_mps2 = np.zeros(cavs.shape)
    # Under "headway" a CAV in front is followed with its command known (car following).
    tf_cav = take(cavs.state.is_cav, np.maximum(near.tf_index, 0)) & near.tf_vehicle.valid
    # A vehicle ahead whose change into the target lane is under way is one of its front
    # vehicles already (scene.joining_target).
    joining_cav = (
        take(cavs.state.is_cav, np.maximum(near.joining_front_index, 0)) & near.joining_front.valid
    )
    fronts = (
        (near.tf_vehicle, tf_cav),
        (near.joining_front, joining_cav),
        (near.target_wall, None),
    )
    for tf, tf_is_cav in fronts:
        has_front = is_lc & tf.valid
        cancel = has_front & (
            (tf.d_long_m <= cfg.d_lc_min_m + horizon.front_margin_m(tf, a, tf_is_cav))
            | tf.risk(cfg.d_safe_m, cfg.ttc_safe_s)
        )
        decel = has_front & (
            tf.risk(cfg.d_safe_m, cfg.ttc_att_s) | tf.risk(cfg.d_att_m, cfg.ttc_safe_s)
        )
        cancel_front |= cancel
        b_lc_mps2 = np.where(
            decel,
            np.maximum(b_lc_mps2, np.minimum(np.abs(nan_to_num(tf.dv_long_mps)), cfg.b_max_mps2)),
            b_lc_mps2,
        )
    return cancel_front, np.where(cancel_front, 0.0, b_lc_mps2)


def _check_rear(
    still_lc: np.ndarray,
    tr: PairKinematics,
    tr_index: np.ndarray,
    b_lc_mps2: np.ndarray,
    horizon: Margins,
    cfg: PSARConfig,
) -> np.ndarray:
    """(..., C) Cancel-LC by a rear vehicle ``k`` of the target lane (kinematics ``tr``,
    vehicle ``tr_index``).

    The first test ``|d_long| <= d_LC,min`` is evaluated on the rear bumper gap
    ``-d_long``, so that vehicles already overlapping alongside (gap < 0) also cancel;
    for every non-overlapping pair this equals the paper's ``|d_long|``.
    """
    has_rear = still_lc & tr.valid
    rear_gap_m = -tr.d_long_m  # bumper gap to the rear vehicle (< 0: overlapping)
    rear_margin_m = horizon.rear_margin_m(tr_index)
    return has_rear & (
        (rear_gap_m <= cfg.d_lc_min_m + rear_margin_m)
        | tr.risk(cfg.d_safe_m, cfg.ttc_safe_s)
        | (
            (tr.risk(cfg.d_safe_m, cfg.ttc_att_s) | tr.risk(cfg.d_att_m, cfg.ttc_safe_s))
            & (b_lc_mps2 != 0.0)
        )
    )


def clashes(
    cavs: Cavs, offset: np.ndarray, moving: np.ndarray, horizon: Margins, cfg: PSARConfig
) -> np.ndarray:
    """(..., C) lane changes ``moving`` that connected CAVs' coordination cancels
    (``cfg.coordinate_lane_changes``; Algorithm 1 is per agent and misses both cases).

    Of two CAVs changing into the same lane, or towards each other into adjacent
    lanes, closer than ``d_safe`` (plus the horizon's margin) along the road, side by
    side (neither sees the other as a target-lane neighbour yet), only the front one
    goes. Nor does a CAV change next to an HDV alongside (within ``d_safe``) in the lane
    beyond the target lane: that one may move into the same lane in the same instant,
    and its intent is unknown.
    """
    state, lane = cavs.state, cavs.lane
    target_lane = lane + offset  # (..., C)
    i_, j_ = (Ellipsis, slice(None), None), (Ellipsis, None, slice(None))  # [..., i, j] axes
    cav_x_m, cav_length_m = take(state.x_m, cavs.index), take(state.length_m, cavs.index)
    dx_m = cav_x_m[j_] - cav_x_m[i_]  # (..., C, C) x_j - x_i
    half_lengths_m = 0.5 * (cav_length_m[i_] + cav_length_m[j_])
    pair_gap_m = np.abs(dx_m) - half_lengths_m
    speed_j = np.broadcast_to(cavs.speed_mps[j_], dx_m.shape)
    need_m = cfg.d_safe_m + horizon.clash_margin_m(cavs.speed_mps[i_], speed_j)
    lanes_apart_after = np.abs(target_lane[i_] - target_lane[j_])  # (..., C, C)
    lanes_apart_now = np.abs(lane[i_] - lane[j_])
    converging = (lanes_apart_after == 0) | (
        (lanes_apart_after == 1) & (lanes_apart_now > lanes_apart_after)
    )
    rows = np.arange(cavs.shape[-1])
    j_first = (dx_m > 0) | ((dx_m == 0) & (rows[None, :] < rows[:, None]))  # j ahead of i
    clash = (moving[i_] & moving[j_] & converging & j_first & (pair_gap_m <= need_m)).any(
        axis=-1
    )  # (..., C) i yields to a CAV ahead entering the same lane
    dx_all_m = state.x_m[..., None, :] - cav_x_m[..., None]  # (..., C, V)
    half_all_m = 0.5 * (state.length_m[..., None, :] + cav_length_m[..., None])
    beyond = (
        (state.active & ~state.is_cav)[..., None, :]  # a CAV's intent is known (above)
        & (state.lane[..., None, :] == (lane + 2 * offset)[..., None])
        & (np.abs(dx_all_m) - half_all_m <= cfg.d_safe_m)
    ).any(axis=-1)  # (..., C)
    return clash | (moving & (offset != 0) & beyond)
