"""The critic's features: small functions, each filling some fields of :class:`CriticState`.

Every function takes the builder's :class:`~.actor_features.Context` and the
:class:`~.frames.Frame` of the instant and returns a dict of fields, as the
actor's do (:mod:`diacc.envs.observation.actor_features`). Two fields come in
two versions, one per value of an option
(:func:`~diacc.envs.observation.builder.features_for`): the node rows
(:func:`vehicle_rows` / :func:`on_road_rows`) and the traffic's clock
(:func:`traffic_features` / :func:`traffic_features_no_clock`).
"""

from __future__ import annotations

import numpy as np

from diacc.envs.observation.actor_features import Context
from diacc.envs.observation.frames import Frame
from diacc.envs.observation.layout import (
    COUNT_SCALE,
    CRITIC_NODE_FEATURES,
    DENSITY_SCALE_VEH_PER_KM,
    MAX_LANES,
    clip_f32,
)
from diacc.sim.state import stack_last, take, take_rows


def vehicle_rows(ctx: Context, frame: Frame) -> dict[str, np.ndarray]:
    """Node rows of a release: row i is vehicle i (padded to ``max_vehicles``)."""
    state = frame.state
    return _nodes(
        ctx, frame, lambda values: values, state.active, frame.nbr, frame.nbr_mask, state.n_vehicles
    )


def on_road_rows(ctx: Context, frame: Frame) -> dict[str, np.ndarray]:
    """Node rows of a demand scenario (``compact_critic``): the vehicles on the road first,
    in index order, so that N bounds the vehicles on the road at once, not V."""
    active = frame.state.active
    vehicle, row_of = _on_road_rows(active, ctx.cfg.max_vehicles)  # (..., R), (..., V)
    node_mask = take(active, vehicle)  # (..., R)
    nbr_mask = take_rows(frame.nbr_mask, vehicle) & node_mask[..., None]
    nbr = take(row_of, take_rows(frame.nbr, vehicle))  # (..., R, K) neighbours' rows
    return _nodes(
        ctx,
        frame,
        lambda values: take(values, vehicle),
        node_mask,
        np.where(nbr_mask, nbr, 0),
        nbr_mask,
        vehicle.shape[-1],
    )


def _nodes(ctx, frame, of_rows, row_mask, row_nbr, row_nbr_mask, n_rows) -> dict[str, np.ndarray]:
    """``nodes``, ``node_mask``, ``neighbours``, ``neighbour_mask`` with the first ``n_rows``
    rows holding vehicles ``of_rows`` ((..., V) -> (..., R)), masks and neighbour rows."""
    sc, state = ctx.scales, frame.state
    lead = state.x_m.shape[:-1]
    n_max, k = ctx.cfg.max_vehicles, ctx.cfg.n_neighbours
    nodes = np.zeros(lead + (n_max, CRITIC_NODE_FEATURES), np.float64)  # (..., N, 6)
    node_mask = np.zeros(lead + (n_max,), bool)
    neighbours = np.zeros(lead + (n_max, k), np.int64)  # (..., N, K)
    neighbour_mask = np.zeros(lead + (n_max, k), bool)
    node_mask[..., :n_rows] = row_mask
    neighbours[..., :n_rows, :] = row_nbr
    neighbour_mask[..., :n_rows, :] = row_nbr_mask
    nodes[..., :n_rows, :] = (
        stack_last(
            [
                of_rows(state.x_m) / sc.route_m,
                of_rows(state.y_m) / sc.road_w_m,
                of_rows(state.speed_mps) / sc.v_max_mps,
                of_rows(state.heading_rad),
                of_rows(state.lane) / sc.lane_norm,
                of_rows(state.is_cav).astype(np.float64),
            ],
        )
        * node_mask[..., :n_rows, None]
    )
    return {
        "nodes": clip_f32(nodes),
        "node_mask": node_mask,
        "neighbours": neighbours,
        "neighbour_mask": neighbour_mask,
    }


def _on_road_rows(active: np.ndarray, n_max: int) -> tuple[np.ndarray, np.ndarray]:
    """The compact critic's rows: vehicles on the road first, in index order.

    Args:
        active: (..., V) bool, at most ``n_max`` True per env (checked on push).

    Returns:
        (..., R) int64 vehicle of each row, R = min(V, n_max) (rows past the
        vehicles on the road hold vehicles off it), and (..., V) int64 row of
        each vehicle on the road (0 for the others).
    """
    n_rows = min(active.shape[-1], n_max)
    vehicle = np.argsort(~active, axis=-1, kind="stable")[..., :n_rows]  # (..., R)
    row_of = np.where(active, np.cumsum(active, axis=-1) - 1, 0)  # (..., V)
    return vehicle.astype(np.int64), row_of


def route_lane_features(ctx: Context, frame: Frame) -> dict[str, np.ndarray]:
    """``lane_stats`` (..., L, 4) per absolute lane over the whole route (density over the
    length on which the lane exists), ``lane_mask`` (..., L): the lane exists."""
    sc, state = ctx.scales, frame.state
    lead, active = state.x_m.shape[:-1], state.active
    # Per absolute lane over the whole route: sums over vehicles, in vehicle order.
    lane = np.where(active, state.lane, MAX_LANES).astype(np.int64)  # inactive: spare bin
    in_lane = lane[..., None] == np.arange(MAX_LANES)  # (..., V, L)

    def per_lane(weights: np.ndarray) -> np.ndarray:  # (..., V) -> (..., L)
        return np.where(in_lane, weights[..., None], 0.0).sum(axis=-2)

    count = per_lane(np.ones(state.x_m.shape))
    n_cav = per_lane(state.is_cav.astype(np.float64))
    speed_sum = per_lane(state.speed_mps)
    lane_mask = np.broadcast_to(np.arange(MAX_LANES) < sc.road.max_lanes, lead + (MAX_LANES,))
    safe = np.maximum(count, 1.0)
    lane_stats = (
        stack_last(
            [
                count / COUNT_SCALE,
                count / np.maximum(sc.lane_len_km, 1e-9) / DENSITY_SCALE_VEH_PER_KM,
                speed_sum / safe / sc.v_max_mps,
                n_cav / safe,
            ],
        )
        * lane_mask[..., None]
    )  # (..., L, 4)
    return {"lane_stats": clip_f32(lane_stats), "lane_mask": lane_mask.copy()}


def road_state_features(ctx: Context, frame: Frame) -> dict[str, np.ndarray]:
    """``road`` (..., 4 S): the static road table."""
    table, lead = ctx.scales.road_table, frame.state.x_m.shape[:-1]
    return {"road": np.broadcast_to(table, lead + table.shape).copy()}


def traffic_features(ctx: Context, frame: Frame) -> dict[str, np.ndarray]:
    """``traffic`` (..., 4): vehicles on the road / N, their mean speed, CAV share, and
    the clock: step / episode length."""
    step_fraction = np.asarray(frame.state.step) / ctx.episode_steps  # (...,)
    return _traffic(ctx, frame, step_fraction)


def traffic_features_no_clock(ctx: Context, frame: Frame) -> dict[str, np.ndarray]:
    """:func:`traffic_features` with the clock always 0 (``critic_step_input=False``): with
    100-step training and 330-step evaluation episodes the value of a truncated episode
    otherwise extrapolates past anything seen."""
    step_fraction = np.asarray(frame.state.step) / ctx.episode_steps  # (...,)
    return _traffic(ctx, frame, np.zeros_like(step_fraction))


def _traffic(ctx: Context, frame: Frame, step_fraction: np.ndarray) -> dict[str, np.ndarray]:
    state, n_max = frame.state, ctx.cfg.max_vehicles
    active = state.active  # (..., V)
    n_active = active.sum(axis=-1)  # (...,)
    safe_active = np.maximum(n_active, 1)
    traffic = stack_last(
        [
            n_active / n_max,
            np.where(active, state.speed_mps, 0.0).sum(axis=-1)
            / safe_active
            / ctx.scales.v_max_mps,
            (state.is_cav & active).sum(axis=-1) / safe_active,
            step_fraction,
        ],
    )
    return {"traffic": clip_f32(traffic)}
