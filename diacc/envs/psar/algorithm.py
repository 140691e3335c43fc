"""The PSAR driver: paper Algorithm 1 from the actor's proposal to the refined actions."""

from __future__ import annotations

import numpy as np

from diacc.config import PSARConfig, SimConfig
from diacc.envs.actions import ACTION_LANE_OFFSET, ACTION_NAMES
from diacc.envs.psar.horizons import HORIZONS
from diacc.envs.psar.lane_change import check_lane_changes, refuse_impossible
from diacc.envs.psar.result import PSARResult, result_of
from diacc.envs.psar.scene import Cavs, find_obstacles
from diacc.envs.safety import SafetyError, check_indices
from diacc.sim.maps import Map
from diacc.sim.state import TrafficState, take


def psar(
    state: TrafficState,
    cav_index: np.ndarray,
    proposed_action: np.ndarray,
    cfg: PSARConfig,
    road: Map,
    sim: SimConfig | None = None,
) -> PSARResult:
    """Refine the actor's actions with paper Algorithm 1, vectorised over CAVs.

    The algorithm is followed block by block; the choices it leaves open are
    those of :mod:`diacc.envs.psar` (the package docstring), each made in
    the block's own module:

    1. A lane change the road does not allow becomes ``remain`` and is flagged
       in ``invalid_lc`` (:mod:`~diacc.envs.psar.lane_change`).
    2. The obstacles around every CAV are found once: target-lane front and
       rear vehicles, same-lane leader, a vehicle cutting in, the ends of the
       target and own lanes (:mod:`~diacc.envs.psar.scene`).
    3. Lines 2-16: Cancel-LC and Decel-LC on the target lane, and the
       connected CAVs' coordination (:mod:`~diacc.envs.psar.lane_change`).
    4. Lines 17-27: the horizon's car following, Force-Brake and
       Suppress-Accel (:mod:`~diacc.envs.psar.horizons`).
    5. Inactive CAVs keep their proposed action with rule NONE.

    A batch of states ((E, V) arrays, :class:`~diacc.sim.state.TrafficState`) is
    filtered in one call with (E, C) slots and actions; every CAV only ever
    meets vehicles of its own env, and the results are those of E calls.

    Args:
        state: Traffic state (a batch) the actions will be applied to.
        cav_index: (..., C) vehicle indices of the CAV slots.
        proposed_action: (..., C) int actions in 0..4.
        cfg: PSAR thresholds and options.
        road: the :class:`~diacc.sim.maps.Map`.
        sim: step length, action size and CAV braking limit (default
            :class:`~diacc.config.SimConfig`).

    Returns:
        :class:`~diacc.envs.psar.result.PSARResult`.
    """
    sim = sim or SimConfig()
    cav_index, proposed = _checked(state, cav_index, proposed_action, road)
    cavs = Cavs.of(state, cav_index)
    horizon = HORIZONS[cfg.horizon](cavs, cfg, road, sim)

    a, invalid_lc, is_lc = refuse_impossible(cavs, proposed, road, sim)
    asked_lane = np.where(is_lc, cavs.lane + ACTION_LANE_OFFSET[a], -1)  # (..., C) -1: none
    near = find_obstacles(cavs, ACTION_LANE_OFFSET[a], road, cfg.queue_gap_m)
    a, b_lc_mps2, mask = check_lane_changes(cavs, a, is_lc, near, horizon, cfg)  # lines 2-16
    a, speed_change, mask, b_lc_mps2 = horizon.car_following(
        a, b_lc_mps2, mask, near, asked_lane
    )  # lines 17-27
    return result_of(a, proposed, speed_change, mask, b_lc_mps2, invalid_lc, cavs.active, sim)


def _checked(
    state: TrafficState, cav_index: np.ndarray, proposed_action: np.ndarray, road: Map
) -> tuple[np.ndarray, np.ndarray]:
    """(..., C) slots and int64 proposals, or a one-line :class:`SafetyError`."""
    cav_index = check_indices(state, cav_index, "cav_index")
    action = np.asarray(proposed_action)
    if action.shape != cav_index.shape:
        raise SafetyError(
            f"proposed_action shape {action.shape} differs from cav_index shape {cav_index.shape}"
        )
    if not np.issubdtype(action.dtype, np.integer):
        raise SafetyError(f"proposed_action must be integers, got dtype {action.dtype}")
    if np.any((action < 0) | (action >= len(ACTION_NAMES))):
        raise SafetyError(f"proposed_action must be in 0..{len(ACTION_NAMES) - 1}")
    if not isinstance(road, Map):
        raise SafetyError(f"road must be a Map, got {type(road).__name__}")
    seg = take(state.segment, cav_index).astype(np.int64)
    if np.any(seg >= len(road.segments)) or np.any(seg < 0):
        raise SafetyError(f"segment index outside the road's {len(road.segments)} segments")
    return cav_index, action.astype(np.int64)
