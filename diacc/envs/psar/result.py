"""What PSAR returns: the refined actions and which rules took effect (codes, bits, counts)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from diacc.config import SimConfig
from diacc.envs.actions import action_speed_change_mps
from diacc.records import Batched, per_env

#: Rule codes of :attr:`PSARResult.rule`.
RULE_NONE, CANCEL_LC, DECEL_LC, FORCE_BRAKE, SUPPR_ACCEL = 0, 1, 2, 3, 4
RULE_NAMES = ("none", "cancel_lc", "decel_lc", "force_brake", "suppr_accel")
#: Bit of each rule code in :attr:`PSARResult.rule_mask` (``1 << (code - 1)``).
RULE_BITS = {code: 1 << (code - 1) for code in range(1, len(RULE_NAMES))}
#: (4,) int64 the bits of rules 1..4, in order (counting rules over arrays of masks)
RULE_BIT_VALUES = np.array([RULE_BITS[c] for c in range(1, len(RULE_NAMES))], dtype=np.int64)


@dataclass
class PSARResult(Batched):
    """Refined actions and what PSAR did, one entry per CAV slot of each env (a
    :class:`~diacc.records.Batched` record).

    ``rule`` is the *last* refinement that took effect (the one that decided
    the final action); ``rule_mask`` has one bit per refinement that took
    effect (:data:`RULE_BITS`), which is what fire rates per rule should
    count. The only combination Algorithm 1 can produce is Cancel-LC followed
    by Force-Brake. A refinement "takes effect" only when it changes the
    outcome: Force-Brake on an action that already brakes at least as hard is
    not reported, and Decel-LC is reported only if the lane change survives
    the rear-vehicle check (its braking is then in ``decel_lc_mps2``).
    ``speed_change_mps`` is what the environment commands: the refined
    action's speed change, Decel-LC's braking and Force-Brake's magnitude
    folded into one number per CAV.
    """

    action: np.ndarray = per_env("E, C")  # int64 refined action
    speed_change_mps: np.ndarray = per_env("E, C")  # float64 commanded change of target speed
    rule: np.ndarray = per_env("E, C")  # int8 last rule code (RULE_*)
    rule_mask: np.ndarray = per_env("E, C")  # int8 bitmask of the rules that took effect
    decel_lc_mps2: np.ndarray = per_env("E, C")  # float64 Decel-LC braking b_lc >= 0 (0 = none)
    invalid_lc: np.ndarray = per_env("E, C")  # bool proposed lane change impossible here
    active: np.ndarray = per_env("E, C")  # bool CAV on the road (inactive: passed through)


def rule_bit(took_effect: np.ndarray, code: int) -> np.ndarray:
    """(..., C) int8: rule ``code``'s bit where it ``took_effect``, else 0 (to OR into a mask)."""
    return np.where(took_effect, RULE_BITS[code], 0).astype(np.int8)


def result_of(
    a: np.ndarray,
    proposed: np.ndarray,
    speed_change: np.ndarray,
    mask: np.ndarray,
    b_lc_mps2: np.ndarray,
    invalid_lc: np.ndarray,
    active: np.ndarray,
    sim: SimConfig,
) -> PSARResult:
    """The :class:`PSARResult` of refined actions; inactive CAVs keep their proposal."""
    rule = np.full(a.shape, RULE_NONE, dtype=np.int8)
    for code in (CANCEL_LC, DECEL_LC, FORCE_BRAKE, SUPPR_ACCEL):  # application order
        rule = np.where(mask & RULE_BITS[code], code, rule).astype(np.int8)
    return PSARResult(
        action=np.where(active, a, proposed).astype(np.int64),
        speed_change_mps=np.where(
            active, speed_change, action_speed_change_mps(proposed, sim)
        ).astype(np.float64),
        rule=rule,
        rule_mask=mask,
        decel_lc_mps2=b_lc_mps2.astype(np.float64),
        invalid_lc=invalid_lc,
        active=active,
    )


def rule_counts(rule_mask: np.ndarray) -> np.ndarray:
    """(4,) int64: how many entries of a bitmask array have each rule 1..4 set."""
    rule_mask = np.asarray(rule_mask).astype(np.int64).reshape(-1)
    return ((rule_mask[:, None] & RULE_BIT_VALUES) != 0).sum(axis=0).astype(np.int64)
