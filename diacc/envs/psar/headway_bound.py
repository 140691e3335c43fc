"""The ``"headway"`` horizon's speed bound: the highest safe end-of-step speed per CAV.

Every front obstacle gives a bound (:func:`~diacc.sim.kinematics.safe_end_speed_mps`):
the same-lane leader, the end of the own lane (not for a CAV leaving it: the
road checked the change's reach) and each CAV ahead that changes, or asks to
change, into the lane in this step (each one, not only the nearest: a nearer
one that only asks may drive on and uncover one that moves in standing;
docs/concepts/psar.md, "Code"). An HDV leader, whose command is unknown, may brake at
once as hard as its style's deceleration (at least the planned rate
``sim.cav.safe_decel_mps2``), and the CAV plans to answer with its full
braking ``sim.cav.decel_mps2``: about one second of headway (Gipps with one
step of reaction). A CAV leader's command of this step is known, so CAVs are
refined front to back (:func:`_front_to_back`): a CAV is bounded once every
CAV it follows is decided, and then needs only ``cfg.min_gap_m`` plus
``cfg.cav_time_gap_s`` of its speed, because from the next step on it learns
of the leader's braking in the step the leader brakes. (A dependency cycle,
possible only between CAVs exactly alongside, keeps the unknown-leader bound:
:func:`_cycle_bound_mps`.)
"""

from __future__ import annotations

import numpy as np

from diacc.config import STYLE_PRESETS, PSARConfig, SimConfig
from diacc.envs.psar.scene import Cavs, Obstacles
from diacc.sim.kinematics import braking_step, safe_end_speed_mps
from diacc.sim.maps import Map
from diacc.sim.state import TrafficState, flat_offsets, stack_last, take, take_last

#: [..., i, j] axes of (..., C, C) pair tables: CAV i (rows) behind CAV j (columns)
I_, J_ = (Ellipsis, slice(None), None), (Ellipsis, None, slice(None))


def headway_bound_mps(
    cavs: Cavs,
    entering_lane: np.ndarray,
    changing: np.ndarray,
    speed_change_mps: np.ndarray,
    slots: np.ndarray,
    near: Obstacles,
    max_brake_mps: np.ndarray | float,
    cfg: PSARConfig,
    road: Map,
    sim: SimConfig,
) -> tuple[np.ndarray, np.ndarray | float]:
    """(..., C) highest safe end-of-step speed per CAV (module docstring), and the speed
    drop each CAV may command (``max_brake_mps``, refined under ``full_brake = "known"``
    once the CAVs it follows are decided).

    Args:
        entering_lane: (..., C) lane each CAV changes or asks to change into (-1: none).
        changing: (..., C) bool, the CAV changes lanes in this step.
        speed_change_mps: (..., C) commands before car following.
        slots: (..., V) each vehicle's agent slot, -1: none
            (:func:`~diacc.envs.psar.scene.slot_of`).
        near: what lies ahead; the merging vehicle is followed like an HDV leader.
        max_brake_mps: (..., C) the speed drop each CAV may command
            (:func:`~diacc.envs.psar.headway.max_brake_mps`).
    """
    lead_slot = np.where(near.sf_vehicle.valid, take(slots, np.maximum(near.sf_index, 0)), -1)
    lead_gap_m = np.where(near.sf_vehicle.valid, near.sf_vehicle.d_long_m, np.inf)  # (..., C)
    fixed_mps = _fixed_bound_mps(cavs, changing, lead_slot, lead_gap_m, near, cfg, road, sim)
    cuts, cut_gap_m = _cut_ins(cavs, entering_lane, changing, cfg)  # (..., C, C) each
    # A lane changer also follows the front CAV of its target lane (an HDV there was
    # checked with the unknown-leader gap before the change was allowed).
    tf_slot = np.where(
        changing & near.tf_vehicle.valid, take(slots, np.maximum(near.tf_index, 0)), -1
    )
    tf_gap_m = np.where(tf_slot >= 0, near.tf_vehicle.d_long_m, np.inf)
    known = ((lead_slot, lead_gap_m), (tf_slot, tf_gap_m))
    followed = _Followed(cavs, cuts, cut_gap_m, known, cfg, sim)
    bound_mps, brake_mps, decided = _front_to_back(
        cavs, fixed_mps, followed, speed_change_mps, max_brake_mps, cfg, road, sim
    )
    known_leaders = cfg.full_brake == "known"
    if decided.all():
        return bound_mps, (brake_mps if known_leaders else max_brake_mps)
    # Left undecided (a cycle): the CAVs ahead are treated as HDVs.
    worst_mps = _cycle_bound_mps(cavs, fixed_mps, known, cut_gap_m, cfg, sim)
    bound_mps = np.where(decided, bound_mps, worst_mps)
    if not known_leaders:
        return bound_mps, max_brake_mps
    return bound_mps, np.where(decided, brake_mps, sim.cav.decel_mps2 * sim.step_s)


def _bound_mps(
    cfg: PSARConfig,
    sim: SimConfig,
    gap_m,
    own_mps,
    lead_step_m,
    lead_end_mps,
    time_gap_s,
    own_decel=None,
    lead_decel=None,
) -> np.ndarray:
    """:func:`~diacc.sim.kinematics.safe_end_speed_mps` at ``gap_m``, inf where it is inf
    (no obstacle); ``own_decel`` defaults to the planned rate."""
    own_decel = sim.cav.safe_decel_mps2 if own_decel is None else own_decel
    with np.errstate(invalid="ignore"):
        out = safe_end_speed_mps(
            gap_m,
            own_mps,
            lead_step_m,
            lead_end_mps,
            sim.step_s,
            own_decel,
            cfg.min_gap_m,
            time_gap_s,
            lead_decel,
        )
    return np.where(np.isfinite(gap_m), out, np.inf)


def _long_speed(state: TrafficState, vehicles: np.ndarray) -> np.ndarray:
    return take(state.speed_mps, vehicles) * np.abs(np.cos(take(state.heading_rad, vehicles)))


def _fixed_bound_mps(
    cavs: Cavs,
    changing: np.ndarray,
    lead_slot: np.ndarray,
    lead_gap_m: np.ndarray,
    near: Obstacles,
    cfg: PSARConfig,
    road: Map,
    sim: SimConfig,
) -> np.ndarray:
    """(..., C) bound behind what no CAV's command decides: an HDV leader (or a CAV one
    without a slot), the vehicle merging in ahead, and the end of the own lane."""
    state, ego_mps, decel = cavs.state, cavs.speed_mps, sim.cav.safe_decel_mps2
    lead = np.maximum(near.sf_index, 0)
    # An HDV leader may brake as hard as its style does, at least at the CAVs' planned
    # rate; behind one the CAV is ready to use its full braking (an emergency).
    style_decel_mps2 = np.array([st.decel_mps2 for st in STYLE_PRESETS[sim.style_preset]])

    def behind_hdv(gap_m: np.ndarray, vehicle: np.ndarray) -> np.ndarray:
        """(..., C, K) bound behind HDVs ``vehicle`` (..., C, K) at ``gap_m``."""
        style = np.maximum(take(state.style, vehicle).astype(np.int64), 0)  # CAV: strictest
        hdv_decel_mps2 = np.maximum(style_decel_mps2[style], decel)  # (..., C)
        step_m, end_mps = braking_step(_long_speed(state, vehicle), sim.step_s, hdv_decel_mps2)
        own_mps = ego_mps[..., None]
        full_mps2 = sim.cav.decel_mps2
        return _bound_mps(cfg, sim, gap_m, own_mps, step_m, end_mps, 0.0, full_mps2, hdv_decel_mps2)

    merging_gap_m = np.where(near.merging.valid, near.merging.d_long_m, np.inf)
    # The leader and the vehicle merging in, as two columns of one call (elementwise).
    hdv_lead_mps, merging_mps = np.moveaxis(
        behind_hdv(
            stack_last([lead_gap_m, merging_gap_m]),
            stack_last([lead, np.maximum(near.merging_index, 0)]),
        ),
        -1,
        0,
    )  # (..., C) each
    wall_gap_m = np.where(near.own_wall.valid & ~changing, near.own_wall.d_long_m, np.inf)
    wall_gap_m = wall_gap_m - exit_room_m(state, cavs.index, road)
    fixed_mps = np.minimum(
        _bound_mps(cfg, sim, wall_gap_m, ego_mps, 0.0, 0.0, 0.0),
        np.where(lead_slot >= 0, np.inf, hdv_lead_mps),
    )
    return np.minimum(fixed_mps, merging_mps)


def _cut_ins(
    cavs: Cavs, entering_lane: np.ndarray, changing: np.ndarray, cfg: PSARConfig
) -> tuple[np.ndarray, np.ndarray]:
    """(..., C, C) [i, j]: whether CAV j cuts into CAV i's lane ahead of it, and the bumper
    gap between them (inf where j does not).

    Every CAV ahead changing into each CAV's lane bounds, not only the nearest: a nearer
    one that only asks (and drives on in its own lane) does not shield the CAV from one
    that moves in, standing, further ahead.
    """
    state, cav_index = cavs.state, cavs.index
    cav_x_m, cav_length_m = take(state.x_m, cav_index), take(state.length_m, cav_index)
    dx_m = cav_x_m[J_] - cav_x_m[I_]
    pair_gap_m = dx_m - 0.5 * (cav_length_m[I_] + cav_length_m[J_])
    # One asking but not changing is yielded to only from far enough behind for it to
    # pass the rear check (gap > d_LC,min once the yielding CAV stands); a CAV closer or
    # alongside drives on and lets it in behind. So of a CAV standing at a lane end and
    # a standing CAV behind it in the target lane one always moves (the zipper's
    # liveness, docs/concepts/psar.md).
    asking = ~changing[J_] & (pair_gap_m <= cfg.d_lc_min_m)
    cuts = (entering_lane[J_] == cavs.lane[I_]) & (entering_lane[J_] >= 0) & (dx_m > 0) & ~asking
    return cuts, np.where(cuts, pair_gap_m, np.inf)


class _Followed:
    """The CAVs each CAV may follow with their command known, as columns of one
    (..., C, C + 4) table: every CAV cutting in, then the same-lane leader and the
    target-lane front CAV (followed: C + 2 columns), then those two again for the threat
    test of "known" (with their own gap and no time gap). One call of the elementwise
    formula per pass gives the values of one call per kind of leader, at a fraction of
    the calls.
    """

    def __init__(
        self, cavs: Cavs, cuts: np.ndarray, cut_gap_m: np.ndarray, known, cfg, sim: SimConfig
    ) -> None:
        self.cfg, self.sim = cfg, sim
        n_cav = cavs.shape[-1]
        lead_cols = stack_last([np.maximum(slot, 0) for slot, _ in known])  # (..., C, 2)
        self.known_leads = stack_last([slot >= 0 for slot, _ in known])  # (..., C, 2)
        self.known_gaps_m = stack_last([gap for _, gap in known])  # (..., C, 2)
        cols = np.concatenate(
            [np.broadcast_to(np.arange(n_cav), cuts.shape), lead_cols, lead_cols], -1
        )  # (..., C, C + 4)
        self.n_followed = n_followed = n_cav + 2
        self.follows = np.concatenate([cuts, self.known_leads], -1)  # (..., C, C + 2)
        self.gap_m = np.concatenate(
            [cut_gap_m, np.where(self.known_leads, self.known_gaps_m, np.inf), self.known_gaps_m],
            -1,
        )  # (..., C, C + 4)
        self.time_gap_s = np.array([cfg.cav_time_gap_s] * n_followed + [0.0, 0.0])  # (C + 4,)
        self.followed_finite = np.isfinite(self.gap_m[..., :n_followed])
        # Gathers of (..., C) values by column, through one flat index made once.
        self._flat_cols = (cols + flat_offsets(cavs.shape[:-1], n_cav, 2)).reshape(-1)
        self._shape = cols.shape
        self.ahead_v0_mps = self.of_cols(cavs.speed_mps)  # (..., C, C + 4)
        self.own_mps = cavs.speed_mps[..., None]

    def of_cols(self, values: np.ndarray) -> np.ndarray:
        """(..., C, C + 4): ``values`` (..., C) of the CAVs in each column."""
        return np.ascontiguousarray(values).reshape(-1).take(self._flat_cols).reshape(self._shape)

    def behind(self, end_mps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """With every CAV ahead ending the step at ``end_mps``: (..., C) bound behind every
        CAV followed (``follows``), and (..., C) whether a known CAV ahead is a threat (it
        brakes harder than planned, is too close, or planned braking falls short)."""
        cfg, sim, n_followed = self.cfg, self.sim, self.n_followed
        planned_mps = sim.cav.safe_decel_mps2 * sim.step_s
        v1 = self.of_cols(end_mps)
        with np.errstate(invalid="ignore"):
            out = safe_end_speed_mps(
                self.gap_m,
                self.own_mps,
                0.5 * (self.ahead_v0_mps + v1) * sim.step_s,
                v1,
                sim.step_s,
                sim.cav.safe_decel_mps2,
                cfg.min_gap_m,
                self.time_gap_s,
            )
        followed = np.where(self.followed_finite, out[..., :n_followed], np.inf)
        planned_end_mps, lead_v1 = out[..., n_followed:], v1[..., n_followed:]
        hard = self.ahead_v0_mps[..., n_followed:] - lead_v1 > planned_mps + 1e-9
        short = planned_end_mps < self.own_mps - planned_mps
        threat = self.known_leads & (hard | short | (self.known_gaps_m < cfg.min_gap_m))
        return followed.min(-1, initial=np.inf), threat.any(-1)


def _front_to_back(
    cavs: Cavs,
    fixed_mps: np.ndarray,
    followed: _Followed,
    speed_change_mps: np.ndarray,
    max_brake_mps: np.ndarray | float,
    cfg: PSARConfig,
    road: Map,
    sim: SimConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Decide the CAVs in passes, each CAV once every CAV it follows is decided.

    Returns (..., C) each: the bound, the speed drop each CAV may command, and whether
    it was decided (not: a dependency cycle).
    """
    state, cav_index, ego_mps = cavs.state, cavs.index, cavs.speed_mps
    n_followed, follows = followed.n_followed, followed.follows
    known_leaders = cfg.full_brake == "known"
    full_mps = sim.cav.decel_mps2 * sim.step_s
    cav_limit_mps = road.speed_limits_mps()[take(state.segment, cav_index).astype(np.int64)]
    brake_mps = np.broadcast_to(np.asarray(max_brake_mps, float), cav_index.shape).copy()
    bound_mps = fixed_mps.copy()
    end_mps = np.zeros(cav_index.shape)  # (..., C) decided end-of-step speed
    decided = ~cavs.active
    for _ in range(cav_index.shape[-1] + 1):  # one pass per CAV a chain can hold, at most
        if np.count_nonzero(decided) == decided.size:  # all decided (.all(), cheaper)
            break
        ready = ~decided & ~(follows & ~followed.of_cols(decided)[..., :n_followed]).any(-1)
        if not np.count_nonzero(ready):
            break
        if np.count_nonzero(follows & ready[..., None]):
            followed_mps, threat = followed.behind(end_mps)
        else:  # no CAV decided now follows one (the first pass: CAVs followed are undecided)
            followed_mps, threat = np.inf, False
        now = np.minimum(fixed_mps, followed_mps)
        bound_mps = np.where(ready, now, bound_mps)
        brake_now = brake_mps
        if known_leaders:
            brake_now = np.where(threat, full_mps, brake_now)
            brake_mps = np.where(ready, brake_now, brake_mps)
        # What the backend makes of the command: within the speed limit (lower is safer).
        end_now = np.minimum(
            end_speed_mps(ego_mps, speed_change_mps, now, brake_now), cav_limit_mps
        )
        end_mps = np.where(ready, end_now, end_mps)
        decided |= ready
    return bound_mps, brake_mps, decided


def _cycle_bound_mps(
    cavs: Cavs, fixed_mps: np.ndarray, known, cut_gap_m: np.ndarray, cfg: PSARConfig, sim: SimConfig
) -> np.ndarray:
    """(..., C) the bound with every CAV ahead treated as an HDV braking at the planned rate."""
    ego_mps, step_s, decel = cavs.speed_mps, sim.step_s, sim.cav.safe_decel_mps2
    worst_mps = fixed_mps
    for slot, gap_m in known:
        speed_mps = take_last(ego_mps, np.maximum(slot, 0))
        gap_m = np.where(slot >= 0, gap_m, np.inf)
        worst_mps = np.minimum(
            worst_mps,
            _bound_mps(cfg, sim, gap_m, ego_mps, *braking_step(speed_mps, step_s, decel), 0.0),
        )
    cut_step_m, cut_end_mps = braking_step(ego_mps[J_], step_s, decel)
    worst_cut_mps = _bound_mps(cfg, sim, cut_gap_m, ego_mps[I_], cut_step_m, cut_end_mps, 0.0)
    return np.minimum(worst_mps, worst_cut_mps.min(-1, initial=np.inf))


def end_speed_mps(
    speed_mps: np.ndarray,
    proposed_mps: np.ndarray,
    bound_mps: np.ndarray,
    max_brake_mps: np.ndarray | float,
) -> np.ndarray:
    """End-of-step speed a CAV commands: its proposal, or the bound (braking <= ``max_brake``)."""
    proposed_end = np.maximum(speed_mps + proposed_mps, 0.0)
    limited = np.maximum(np.maximum(bound_mps, speed_mps - max_brake_mps), 0.0)
    return np.where(proposed_end <= np.maximum(bound_mps, 0.0), proposed_end, limited)


def exit_room_m(state: TrafficState, cav_index: np.ndarray, road: Map) -> np.ndarray:
    """(..., C) how far before its lane's end a CAV must stop to still be able to leave.

    A lane whose neighbours end no later (the outer lane of a two-lane drop)
    can only be left into a lane that ends as soon, and a change needs the
    target lane to last the vehicle's length beyond its centre even from
    standstill (:meth:`Map.lane_change_allowed`): stopping at the very end
    would trap the CAV. So its wall moves back to where the change is still
    allowed, plus half a metre. 0 where a neighbour outlasts the lane.
    """
    seg = take(state.segment, cav_index).astype(np.int64)
    lane = take(state.lane, cav_index).astype(np.int64)
    own_ends_m, exit_ends_m = road.exit_ends_m()  # (S, L) each
    own_end_m, exit_end_m = own_ends_m[seg, lane], exit_ends_m[seg, lane]  # (..., C)
    length_m = take(state.length_m, cav_index)
    trapped = np.isfinite(own_end_m) & np.isfinite(exit_end_m) & (exit_end_m <= own_end_m)
    with np.errstate(invalid="ignore"):  # inf - inf where no lane ends
        room_m = own_end_m - (exit_end_m - 0.5 * length_m - 0.5)  # front stays behind this
    return np.where(trapped, np.maximum(room_m, 0.0), 0.0)
