"""PSAR's horizons (``PSARConfig.horizon``): how far ahead the rule blocks look.

A horizon sizes the margins that the lane-change checks add to Algorithm 1's
distances, and chooses the car following (lines 17-27). Each is one class:

* ``"paper"`` (:class:`PaperHorizon`): the fixed thresholds, no margin.
* ``"stopping"`` (:class:`StoppingHorizon`): every distance lengthened by
  Gipps' safe gap (:func:`~diacc.sim.kinematics.safe_gap_m`): one decision
  step of reaction, then braking at the CAV's planned deceleration while the
  vehicle ahead brakes as hard (a rear HDV reacts at once, a rear CAV after
  a step); car following with the paper's thresholds so lengthened
  (:func:`~diacc.envs.psar.car_following.threshold_car_following`).
* ``"headway"`` (:class:`HeadwayHorizon`): the stopping gaps plus the
  standstill gap car following keeps, a CAV's platoon gap behind a CAV whose
  command is known, and a rear CAV that brakes for a changer at once; car
  following by braking physics alone
  (:func:`~diacc.envs.psar.headway.headway_car_following`).
"""

from __future__ import annotations

import numpy as np

from diacc.config import PSARConfig, SimConfig
from diacc.envs.actions import REMAIN, action_speed_change_mps
from diacc.envs.psar.car_following import threshold_car_following
from diacc.envs.psar.headway import headway_car_following
from diacc.envs.psar.scene import Cavs, Obstacles
from diacc.envs.safety import PairKinematics
from diacc.sim.kinematics import nan_to_num, safe_gap_m
from diacc.sim.maps import Map
from diacc.sim.state import take

#: (..., C) refined action, speed change (m/s), rule mask, Decel-LC braking (m/s^2)
Refined = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


class PaperHorizon:
    """``"paper"``: Algorithm 1's fixed distances; every margin is 0."""

    def __init__(self, cavs: Cavs, cfg: PSARConfig, road: Map, sim: SimConfig) -> None:
        self.cavs, self.cfg, self.road, self.sim = cavs, cfg, road, sim

    def front_margin_m(
        self, kin: PairKinematics, action: np.ndarray, front_is_cav: np.ndarray | None = None
    ) -> np.ndarray:
        """(..., C) extra distance kept behind front obstacles ``kin`` for ``action``;
        ``front_is_cav`` (lane-change checks only): the obstacle is a CAV."""
        return np.zeros(self.cavs.shape)

    def rear_margin_m(self, rear_index: np.ndarray) -> np.ndarray | float:
        """(..., C) extra distance a lane changer keeps ahead of the target lane's rear
        vehicles ``rear_index`` (..., C)."""
        return 0.0

    def clash_margin_m(self, speed_i_mps: np.ndarray, speed_j_mps: np.ndarray):
        """(..., C, C) extra distance between two CAVs changing into each other's way,
        CAV i behind CAV j."""
        return 0.0

    def holds_short(self, front: PairKinematics, gap_m: np.ndarray) -> np.ndarray | bool:
        """(..., C) whether a CAV ``gap_m`` behind ``front`` counts as closing in even
        at equal speeds (Force-Brake's distance branch)."""
        return False

    def car_following(
        self, a: np.ndarray, b_lc_mps2: np.ndarray, mask: np.ndarray, near: Obstacles, asked_lane
    ) -> Refined:
        """Lines 17-27 after the lane-change checks; ``asked_lane`` (..., C): the lane each
        CAV asked to change into (-1: none)."""
        return threshold_car_following(
            self, self.cavs, a, b_lc_mps2, mask, near, self.cfg, self.sim
        )


class StoppingHorizon(PaperHorizon):
    """``"stopping"``: the paper's distances lengthened by Gipps' safe gap.

    The authors' distances come from a 15 m/s road; at 25 m/s a CAV needs
    about 60 m to brake for a standing queue, and a leader that brakes hard
    needs about one second of headway.
    """

    def front_margin_m(self, kin, action, front_is_cav=None):
        """Gipps' safe gap, with the speed the CAV reaches by the end of the step if
        it accelerates as proposed (braking proposals are judged at the current speed)."""
        return np.where(kin.valid, self._front_gap_m(kin, action, front_is_cav), 0.0)

    def _front_gap_m(self, kin, action, front_is_cav):
        sim, ego_mps = self.sim, self.cavs.speed_mps
        lead_speed_mps = ego_mps - nan_to_num(kin.dv_long_mps)  # 0 for a wall
        end_speed_mps = ego_mps + np.maximum(action_speed_change_mps(action, sim), 0)
        return safe_gap_m(
            ego_mps, lead_speed_mps, sim.step_s, sim.cav.safe_decel_mps2, end_speed_mps
        )

    def rear_margin_m(self, rear_index):
        """The rear vehicle must be able to brake for the CAV (:meth:`_rear_reaction`)."""
        state = self.cavs.state
        rear = np.maximum(rear_index, 0)
        rear_speed_mps = take(state.speed_mps, rear) * np.abs(np.cos(take(state.heading_rad, rear)))
        reaction_s, rear_end_mps, extra_m = self._rear_reaction(
            rear_speed_mps, take(state.is_cav, rear)
        )
        return extra_m + safe_gap_m(
            rear_speed_mps,
            self.cavs.speed_mps,
            reaction_s,
            self.sim.cav.safe_decel_mps2,
            rear_end_mps,
        )

    def _rear_reaction(self, rear_speed_mps: np.ndarray, rear_cav: np.ndarray):
        """(reaction time s, speed at the end of the reaction m/s, extra gap m) of rear
        vehicles: a rear CAV reacts after a step and may accelerate during it."""
        reaction_s = np.where(rear_cav, self.sim.step_s, 0.0)
        rear_end_mps = rear_speed_mps + np.where(rear_cav, self.sim.speed_change_mps, 0.0)
        return reaction_s, rear_end_mps, 0.0

    def clash_margin_m(self, speed_i_mps, speed_j_mps):
        return safe_gap_m(speed_i_mps, speed_j_mps, self.sim.step_s, self.sim.cav.safe_decel_mps2)

    def holds_short(self, front, gap_m):
        """A gap shorter than the one a lane change needs to enter (d_LC,min + Gipps) is
        closed in effect, even at equal speeds: the leader may brake in this very step,
        and a CAV that answers a step late keeps closing at that step's braking until it
        hits (``diacc bench --safety``, docs/concepts/psar.md). Judged at the CAV's
        current speed (as for ``remain``), whatever it proposed; a standing CAV is not
        closing."""
        hold_m = self.cfg.d_lc_min_m + self.front_margin_m(front, np.full(self.cavs.shape, REMAIN))
        return (self.cavs.speed_mps > 0.0) & (gap_m <= hold_m)


class HeadwayHorizon(StoppingHorizon):
    """``"headway"``: the stopping gaps sized for car following by braking physics alone.

    A lane changer keeps, beyond Gipps' gap, the standstill gap car following
    will keep (``cfg.min_gap_m``), and behind a CAV whose command will be known
    only the platoon gap (``cfg.min_gap_m`` + ``cfg.cav_time_gap_s``); a rear
    CAV learns of the change in this step (it is refined after the changer),
    brakes for it at once and then restores its full gap.
    """

    def _front_gap_m(self, kin, action, front_is_cav):
        cfg, ego_mps = self.cfg, self.cavs.speed_mps
        gap_m = super()._front_gap_m(kin, action, front_is_cav)
        gap_m = gap_m + max(cfg.min_gap_m - cfg.d_lc_min_m, 0.0)  # the standstill gap
        if front_is_cav is not None:  # a CAV's command will be known: the platoon gap
            platoon_m = cfg.cav_time_gap_s * ego_mps + cfg.min_gap_m - cfg.d_lc_min_m
            gap_m = np.where(front_is_cav, np.maximum(platoon_m, 0.0), gap_m)
        return gap_m

    def _rear_reaction(self, rear_speed_mps, rear_cav):
        extra_m = np.where(rear_cav, self.cfg.cav_time_gap_s * rear_speed_mps, 0.0)
        return 0.0, rear_speed_mps, extra_m

    def car_following(self, a, b_lc_mps2, mask, near, asked_lane):
        """:func:`~diacc.envs.psar.headway.headway_car_following`; with
        ``cfg.cooperative_merge`` off, no CAV opens a gap for one that only asks."""
        if not self.cfg.cooperative_merge:
            asked_lane = np.full(self.cavs.shape, -1)
        return headway_car_following(
            self.cavs, a, b_lc_mps2, mask, near, asked_lane, self.cfg, self.road, self.sim
        )


#: ``PSARConfig.horizon`` -> its class: the one place an option picks its rule blocks.
HORIZONS: dict[str, type[PaperHorizon]] = {
    "paper": PaperHorizon,
    "stopping": StoppingHorizon,
    "headway": HeadwayHorizon,
}
