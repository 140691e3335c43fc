"""PSAR, the paper's Algorithm 1: the safety filter between the actor and the simulator.

The actor proposes one action per CAV; :func:`psar` refines it with four
rules (Cancel-LC, Decel-LC, Force-Brake, Suppress-Accel) from the gaps and
TTCs of :mod:`diacc.envs.safety`, and reports which rules took effect
(:class:`PSARResult`), which the metrics and the training logs count
(:func:`rule_counts`). Options and thresholds: :class:`~diacc.config.PSARConfig`.

One module per block, the driver reading top to bottom:

* ``algorithm``: :func:`psar`, the driver.
* ``scene``: the CAV slots and their obstacles, found once.
* ``lane_change``: lines 2-16 and the road's and connected CAVs' checks.
* ``horizons``: ``paper`` / ``stopping`` / ``headway``, the margins each adds
  and the car following each picks (``HORIZONS``, the one place the option
  is read).
* ``car_following``: lines 17-27 with thresholds (``paper``, ``stopping``).
* ``headway`` and ``headway_bound``: car following by braking physics.
* ``result``: :class:`PSARResult`, rule codes and counts.

The choices Algorithm 1 leaves open:

* Target lane = ego lane + 1 for ``left``, - 1 for ``right``. A lane
  change the road does not allow (``lane_change_allowed``: the target lane
  is missing here or ends within the change's reach; the same rule the
  backends apply) is replaced by ``remain`` *before* Algorithm 1 and
  flagged in ``invalid_lc``, so the car-following checks still run;
  without this a policy could dodge them by asking for an impossible
  change.
* Lane ends are standing obstacles: the front vehicle of the car-following
  block is the nearer of the same-lane leader and the end of the ego
  lane; the front vehicle of the lane-change checks is the nearer of the
  target-lane leader and the end of the target lane
  (:func:`~diacc.envs.safety.lane_end_kinematics`).
* ``cfg.coordinate_lane_changes`` (default on): of two CAVs changing into
  the same lane, or towards each other into adjacent lanes, closer than
  ``d_safe`` (plus the safe gap of the "stopping" horizon) along the
  road, the rear one is cancelled (Cancel-LC). Algorithm 1 is per agent
  and neither would see the other; connected CAVs know each other's
  intent. For the same reason a CAV does not change lanes next to an
  HDV alongside (within ``d_safe``) in the lane beyond the target
  lane, whose intent it cannot know.
* Rear vehicle ``k``: the first cancel test ``|d_long| <= d_LC,min`` is
  evaluated on the rear bumper gap ``-d_long`` so that vehicles already
  overlapping alongside (gap < 0) also cancel; for every non-overlapping
  pair this equals the paper's ``|d_long|``.
* Decel-LC: ``b_lc = min(|dv_long|, b_max)`` with the target-lane front
  vehicle, applied over the step of the lane change; returned in
  ``decel_lc_mps2``. It is zeroed if the change is then cancelled.
* The car-following block (lines 17-27) uses the front obstacle in the
  ego's current lane, and runs for actions {remain, accelerate,
  decelerate} including lane changes cancelled above. Its second branch
  sets ``remain`` even if the proposal was ``decelerate`` (the gap is
  small but not closing), exactly as the pseudocode says.
* Force-Brake magnitude (``cfg.force_brake``): ``"cancel"`` (default)
  lowers the target speed by ``max(dv_action, c + dv_action)`` for the
  distance trigger (line 19) and ``max(dv_action, c)`` for the TTC trigger
  (line 23), with ``c`` the closing speed and ``dv_action`` the
  decelerate action's step (the authors' own implementation), bounded by
  the CAV's planned braking ``sim.cav.safe_decel_mps2`` over the step;
  ``"paper"`` is the literal reading, action 4 = one ``dv_action`` step,
  which cannot stop a CAV that closes faster than that.
* Horizon (``cfg.horizon``): ``"stopping"`` (an earlier default)
  lengthens d_warn and d_att, and the lane-change cancel distance d_LC,min
  to the target-lane front and rear vehicles, by Gipps' safe gap
  (:func:`~diacc.sim.kinematics.safe_gap_m`): one decision step of reaction,
  then braking at the CAV's planned deceleration while the vehicle ahead
  brakes as hard (a rear HDV reacts at once, a rear CAV after a step).
  ``"paper"`` uses the fixed thresholds. Under ``"stopping"`` a moving CAV
  whose gap is at most the one a lane change needs to enter (d_LC,min plus
  the safe gap at its current speed) gets Force-Brake's distance branch
  (line 19) even when it is not closing: else it holds a gap from which it
  cannot answer a leader that brakes in the same step, and closes at one
  step's braking until it hits. ``"headway"`` (the default) replaces the
  car-following block (lines 17-27) by braking physics alone: about one
  second behind an HDV, ``cfg.min_gap_m`` + ``cfg.cav_time_gap_s`` behind a
  CAV whose refined command of this step is known (CAVs are refined front
  to back); the lane-change checks keep their structure with these gaps (a
  rear CAV learns of the change in this step, so it needs no reaction
  step), and CAVs open a gap for a CAV that asks to merge in front of them
  (``cfg.cooperative_merge``); a vehicle cutting in (below) is an HDV
  leader there.
* Cut-ins: the nearest vehicle ahead in a neighbouring lane whose centre
  has left its lane's centre line towards the ego lane by more than
  ``CUT_IN_DRIFT_M`` (a lane change into the ego lane under way) is a front
  obstacle of the car-following block too. Without it the CAV sees the
  merging vehicle only once its centre crosses the lane boundary; on SUMO,
  where an LC2013 driver may start a merge from standstill 15-20 m ahead of
  a CAV (its gap check assumes the CAV keeps its speed), the CAV would
  meanwhile accelerate into a gap it can no longer brake for (measured with
  ``diacc bench --safety``: docs/concepts/psar.md).
* Inactive CAVs keep their proposed action with rule NONE.
"""

from diacc.envs.psar.algorithm import psar
from diacc.envs.psar.result import (
    CANCEL_LC,
    DECEL_LC,
    FORCE_BRAKE,
    RULE_BIT_VALUES,
    RULE_BITS,
    RULE_NAMES,
    RULE_NONE,
    SUPPR_ACCEL,
    PSARResult,
    rule_counts,
)
from diacc.envs.psar.scene import CUT_IN_DRIFT_M

__all__ = [
    "CANCEL_LC",
    "CUT_IN_DRIFT_M",
    "DECEL_LC",
    "FORCE_BRAKE",
    "RULE_BITS",
    "RULE_BIT_VALUES",
    "RULE_NAMES",
    "RULE_NONE",
    "SUPPR_ACCEL",
    "PSARResult",
    "psar",
    "rule_counts",
]
