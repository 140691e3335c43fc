"""The actor's features: small functions, each filling some fields of :class:`ActorObs`.

Every function takes the builder's :class:`Context`, the :class:`~.frames.Frame`
of the instant and the CAV slots (:class:`Slots`), and returns a dict of
fields (float fields clipped to float32, rows of CAVs not alive zeroed);
:class:`~diacc.envs.observation.builder.ObservationBuilder` merges the dicts
of its chosen functions into one :class:`ActorObs`. The layout of each field
is :mod:`diacc.envs.observation.layout`'s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from diacc.config import ObservationConfig
from diacc.envs.observation.frames import Frame, History
from diacc.envs.observation.layout import (
    COUNT_SCALE,
    DENSITY_SCALE_VEH_PER_KM,
    DX_SCALE_M,
    LANE_END_SCALE_M,
    N_ACTIONS,
    clip_f32,
)
from diacc.envs.observation.scales import MapScales
from diacc.sim.state import TrafficState, flat_offsets, stack_last, take, take_rows


@dataclass(frozen=True)
class Context:
    """What every feature function may read besides the instant: the map's scales, the
    config's sizes and the episode length (the critic's clock)."""

    scales: MapScales
    cfg: ObservationConfig
    episode_steps: int


@dataclass(slots=True)
class Slots:
    """The CAV slots observed and the per-call inputs, gathered once; (..., C) each."""

    index: np.ndarray  # vehicle index of each slot
    alive: np.ndarray  # bool on the road
    x_m: np.ndarray
    y_m: np.ndarray
    speed_mps: np.ndarray
    lane: np.ndarray  # int64
    segment: np.ndarray  # int64
    action_memory: np.ndarray  # (..., C, 2) proposed and refined action of the last step
    last_refined_action: np.ndarray  # (..., V) refined action every vehicle executed

    @classmethod
    def of(cls, state: TrafficState, cav_index, action_memory, last_refined_action) -> Slots:
        return cls(
            index=cav_index,
            alive=take(state.active, cav_index),
            x_m=take(state.x_m, cav_index),
            y_m=take(state.y_m, cav_index),
            speed_mps=take(state.speed_mps, cav_index),
            lane=take(state.lane, cav_index).astype(np.int64),
            segment=take(state.segment, cav_index).astype(np.int64),
            action_memory=action_memory,
            last_refined_action=last_refined_action,
        )


def self_features(ctx: Context, frame: Frame, slots: Slots) -> dict[str, np.ndarray]:
    """``self_state`` (..., C, 6): position, speed, heading, lane, room to the lane's end."""
    sc, state = ctx.scales, frame.state
    lane_clip = np.minimum(np.maximum(slots.lane, 0), sc.road.max_lanes - 1)
    seg_clip = np.minimum(np.maximum(slots.segment, 0), len(sc.road.segments) - 1)
    to_end_m = sc.lane_end_m[seg_clip, lane_clip] - slots.x_m  # (..., C)
    self_state = stack_last(
        [
            slots.x_m / sc.route_m,
            slots.y_m / sc.road_w_m,
            slots.speed_mps / sc.v_max_mps,
            take(state.heading_rad, slots.index),
            slots.lane / sc.lane_norm,
            np.minimum(np.maximum(to_end_m / LANE_END_SCALE_M, 0.0), 1.0),
        ],
    )  # (..., C, 6)
    return {"self_state": clip_f32(self_state * slots.alive[..., None])}


def neighbour_features(ctx: Context, frame: Frame, slots: Slots) -> dict[str, np.ndarray]:
    """The ego's and its K nearest neighbours' trajectories in the ego's frame, split by
    type (each set compacted nearest first), and each neighbouring CAV's last action."""
    state, k, alive = frame.state, ctx.cfg.n_neighbours, slots.alive
    rows = slots.index[..., None]  # (..., C, 1)
    sel = take_rows(frame.nbr, slots.index)  # (..., C, K)
    sel_mask = take_rows(frame.nbr_mask, slots.index)  # (..., C, K)
    sel_cav = sel_mask & take(state.is_cav, sel)  # (..., C, K)
    hdv_idx, hdv_mask = compact(sel, sel_mask & ~sel_cav)  # (..., C, K) each
    cav_idx, cav_mask = compact(sel, sel_cav)

    # Node histories in the ego's current frame, all sets in one gather.
    idx = np.concatenate([rows, hdv_idx, cav_idx], axis=-1)  # (..., C, 1+2K)
    valid = np.concatenate([alive[..., None], hdv_mask, cav_mask], axis=-1)
    nodes = relative_nodes(ctx, frame.hist, state, idx, slots)  # (..., C, M, T, F)
    nodes *= valid[..., None, None]
    cav_prev_action = np.where(cav_mask, take(slots.last_refined_action, cav_idx), 0)
    cav_prev_action = cav_prev_action.astype(np.int64)
    return {
        "ego_hist": clip_f32(nodes[..., 0, :, :]),  # (..., C, T, F)
        "hdv_nodes": clip_f32(nodes[..., 1 : 1 + k, :, :]),  # (..., C, K, T, F)
        "hdv_mask": hdv_mask & alive[..., None],
        "cav_nodes": clip_f32(nodes[..., 1 + k :, :, :]),
        "cav_mask": cav_mask & alive[..., None],
        "cav_prev_action": cav_prev_action * alive[..., None],
    }


def relative_nodes(
    ctx: Context, hist: History, state: TrafficState, idx: np.ndarray, slots: Slots
) -> np.ndarray:
    """Node features (..., C, M, T, F) of vehicles ``idx`` (..., C, M) in each ego's frame."""
    sc, steps, n_veh = ctx.scales, ctx.cfg.history_steps, state.n_vehicles
    ego_x, ego_y, ego_v = slots.x_m, slots.y_m, slots.speed_mps
    # Vehicles only leave, so an inactive past entry means "not yet on the
    # road": use the earliest step at which the vehicle was active instead.
    first = np.argmax(hist.active, axis=-2)  # (..., V) 0 if never active
    t_of = np.maximum(np.arange(steps), take(first, idx)[..., None])  # (..., C, M, T)
    lead = state.x_m.shape[:-1]
    # Into the flattened (..., T, V) history of every env: one index for the four
    # gathers (a flat take costs a fraction of fancy indexing by env and vehicle).
    flat = t_of * n_veh + idx[..., None] + flat_offsets(lead, steps * n_veh, 3)

    def gather(a: np.ndarray) -> np.ndarray:  # (..., T, V) -> (..., C, M, T)
        return np.ascontiguousarray(a).reshape(-1).take(flat)

    x, y = gather(hist.x_m), gather(hist.y_m)
    v, heading = gather(hist.speed_mps), gather(hist.heading_rad)
    is_cav = take(state.is_cav, idx)[..., None].astype(np.float64)  # (..., C, M, 1)
    return stack_last(  # (stack_last broadcasts is_cav over T)
        [
            (x - ego_x[..., None, None]) / DX_SCALE_M,
            (y - ego_y[..., None, None]) / sc.lane_w_m,
            (v - ego_v[..., None, None]) / sc.v_max_mps,
            heading,
            v / sc.v_max_mps,
            is_cav,
        ],
    )  # (..., C, M, T, F)


def ego_lane_features(ctx: Context, frame: Frame, slots: Slots) -> dict[str, np.ndarray]:
    """Ego / left / right lane statistics (..., C, 3, 4) within ``lane_window_m`` of the
    ego, and whether each lane exists in the ego's segment (..., C, 3)."""
    sc, state, w_m = ctx.scales, frame.state, ctx.cfg.lane_window_m
    cav_index = slots.index
    target = slots.lane[..., None] + np.array([0, 1, -1])  # (..., C, 3) absolute lanes
    seg = np.minimum(np.maximum(slots.segment, 0), len(sc.road.segments) - 1)
    exists = sc.exists_pad[
        seg[..., None], np.minimum(np.maximum(target + 1, 0), sc.road.max_lanes + 1)
    ]
    ego_x = slots.x_m  # (..., C)
    in_win = (np.abs(state.x_m[..., None, :] - ego_x[..., None]) <= w_m) & state.active[
        ..., None, :
    ]  # (..., C, V)
    in_win &= np.arange(state.n_vehicles) != cav_index[..., None]  # ego excluded
    hit = in_win[..., None, :] & (
        state.lane[..., None, None, :] == target[..., None]
    )  # (..., C, 3, V)
    count = hit.sum(axis=-1).astype(np.float64)  # (..., C, 3)
    n_cav = (hit & state.is_cav[..., None, None, :]).sum(axis=-1)
    speed_sum = (hit * state.speed_mps[..., None, None, :]).sum(axis=-1)
    win_km = (np.minimum(ego_x + w_m, sc.route_m) - np.maximum(ego_x - w_m, 0.0)) / 1000.0
    safe = np.maximum(count, 1.0)
    stats = stack_last(
        [
            count / COUNT_SCALE,
            count / np.maximum(win_km, 1e-9)[..., None] / DENSITY_SCALE_VEH_PER_KM,
            speed_sum / safe / sc.v_max_mps,
            n_cav / safe,
        ],
    )  # (..., C, 3, 4)
    exists &= slots.alive[..., None]  # the lane mask
    stats *= exists[..., None]
    return {"lane_stats": clip_f32(stats), "lane_mask": exists}


def road_features(ctx: Context, frame: Frame, slots: Slots) -> dict[str, np.ndarray]:
    """``road`` (..., C, 4 S): the static road table, per CAV alive."""
    return {"road": clip_f32(ctx.scales.road_table * slots.alive[..., None])}  # (..., C, 4S)


def memory_features(ctx: Context, frame: Frame, slots: Slots) -> dict[str, np.ndarray]:
    """What passes through: the last step's actions, every action allowed, alive."""
    return {
        "action_memory": slots.action_memory.astype(np.int64, copy=True),
        "action_mask": np.ones(slots.index.shape + (N_ACTIONS,), bool),
        "alive": slots.alive.copy(),
    }


def compact(idx: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Move kept entries of each row to the front, order preserved; pad with 0 / False.

    Args:
        idx: (..., R, K) int indices.
        keep: (..., R, K) bool which entries belong to the set.
    """
    k = idx.shape[-1]
    # Each kept entry's place among the kept ones; the others go to a spare column K.
    place = np.where(keep, np.cumsum(keep, axis=-1) - 1, k)  # (..., R, K)
    n_rows = math.prod(keep.shape[:-1])
    out = np.zeros((n_rows, k + 1), np.int64)
    out[np.arange(n_rows)[:, None], place.reshape(n_rows, k)] = idx.reshape(n_rows, k)
    mask = np.arange(k) < keep.sum(axis=-1, keepdims=True)
    return out[:, :k].reshape(idx.shape), mask
