"""Algorithm 1's car following (lines 17-27) with distance and TTC thresholds.

The ``"paper"`` and ``"stopping"`` horizons; their thresholds differ only by the
horizon's margins (:mod:`diacc.envs.psar.horizons`). The block runs for
actions {remain, accelerate, decelerate}, lane changes cancelled before
included, against each front obstacle in the ego's current lane (the leader,
the lane's end, a vehicle cutting in); the most demanding outcome wins.
Its second branch sets ``remain`` even if the proposal was ``decelerate``
(the gap is small but not closing), exactly as the pseudocode says.
"""

from __future__ import annotations

import numpy as np

from diacc.config import PSARConfig, SimConfig
from diacc.envs.actions import ACCELERATE, DECELERATE, REMAIN, action_speed_change_mps
from diacc.envs.psar.result import FORCE_BRAKE, SUPPR_ACCEL, rule_bit
from diacc.envs.psar.scene import Cavs, Margins, Obstacles
from diacc.envs.safety import PairKinematics
from diacc.sim.kinematics import nan_to_num


def threshold_car_following(
    horizon: Margins,
    cavs: Cavs,
    a: np.ndarray,
    b_lc_mps2: np.ndarray,
    mask: np.ndarray,
    near: Obstacles,
    cfg: PSARConfig,
    sim: SimConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Force-Brake (branches 1 and 3) and Suppress-Accel (branches 2 and 4) on actions
    ``a`` (..., C). Returns ``(action, speed change, rule mask, b_lc)``."""
    shape = cavs.shape
    longitudinal = cavs.active & ((a == REMAIN) | (a == ACCELERATE) | (a == DECELERATE))
    fires_brake = np.zeros(shape, dtype=bool)  # branch 1 or 3 fired for some obstacle
    fires_suppress = np.zeros(shape, dtype=bool)  # branch 2 or 4 fired for some obstacle
    need_mps = np.zeros(shape)  # "cancel" braking the fired branches ask for
    for front in (near.sf_vehicle, near.own_wall, near.merging):
        br1, br2, br3, br4 = _branches(horizon, longitudinal & front.valid, front, a, cfg)
        closing_mps = nan_to_num(front.dv_long_mps)  # (..., C)
        need_mps = np.maximum(need_mps, np.where(br1, closing_mps + sim.speed_change_mps, 0.0))
        need_mps = np.maximum(need_mps, np.where(br3, closing_mps, 0.0))
        fires_brake |= br1 | br3
        fires_suppress |= br2 | br4

    speed_change = action_speed_change_mps(a, sim) - b_lc_mps2 * sim.step_s  # (..., C)
    brake_mps, brake = FORCE_BRAKES[cfg.force_brake](a, fires_brake, need_mps, speed_change, sim)
    suppress = fires_suppress & ~fires_brake & (a != REMAIN)
    a = np.where(fires_brake, np.where(brake, DECELERATE, a), np.where(suppress, REMAIN, a))
    speed_change = np.where(brake, -brake_mps, np.where(suppress, 0.0, speed_change))
    mask |= rule_bit(brake, FORCE_BRAKE)
    mask |= rule_bit(suppress, SUPPR_ACCEL)
    return a, speed_change, mask, b_lc_mps2


def _branches(
    horizon: Margins,
    has_leader: np.ndarray,
    front: PairKinematics,
    a: np.ndarray,
    cfg: PSARConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(..., C) bool each: which of the four branches fires for front obstacle ``front``
    (1: brake, near and closing; 2: remain, near; 3: brake, TTC; 4: remain, TTC)."""
    with np.errstate(invalid="ignore"):
        d_m = np.where(front.valid, front.d_long_m, np.inf)
    ttc_s = front.ttc_s
    extra_m = horizon.front_margin_m(front, a)
    d_warn_m, d_att_m = cfg.d_warn_m + extra_m, cfg.d_att_m + extra_m  # (..., C)
    closing = ttc_s < np.inf  # paper's TTC > 0
    too_short = horizon.holds_short(front, d_m)
    br1 = has_leader & (d_m <= d_warn_m) & (closing | too_short)
    br2 = has_leader & ~br1 & ((d_m <= cfg.d_safe_m) | ((d_m <= d_warn_m) & (a == ACCELERATE)))
    br3 = has_leader & ~br1 & ~br2 & (np.abs(d_m) <= d_att_m) & (ttc_s <= cfg.ttc_warn_s)
    br4 = has_leader & ~br1 & ~br2 & ~br3 & (np.abs(d_m) <= d_att_m)
    br4 &= (ttc_s <= cfg.ttc_att_s) & (a == ACCELERATE)
    return br1, br2, br3, br4


def _cancel_brake(a, fires_brake, need_mps, speed_change, sim: SimConfig):
    """``force_brake="cancel"``: lower the target speed by ``max(dv_action, c + dv_action)``
    (distance branch) or ``max(dv_action, c)`` (TTC branch), ``c`` the closing speed,
    bounded by the planned braking over the step; reported only where that brakes harder
    than the action already does. Returns (..., C) braking m/s and whether it applies."""
    max_brake_mps = sim.cav.safe_decel_mps2 * sim.step_s  # largest planned drop in one step
    brake_mps = np.minimum(np.maximum(need_mps, sim.speed_change_mps), max_brake_mps)
    return brake_mps, fires_brake & (-brake_mps < speed_change)


def _paper_brake(a, fires_brake, need_mps, speed_change, sim: SimConfig):
    """``force_brake="paper"``: Force-Brake is the decelerate action (one ``dv_action``)."""
    return np.full(a.shape, sim.speed_change_mps), fires_brake & (a != DECELERATE)


#: ``PSARConfig.force_brake`` -> how hard Force-Brake brakes.
FORCE_BRAKES = {"cancel": _cancel_brake, "paper": _paper_brake}
