"""Random but well-formed observation containers, for tests and benchmarks.

They follow the documented layout of :mod:`diacc.envs.observation` (padding zero and
masked, valid neighbours first, neighbour indices pointing at other active
vehicles) without needing a simulator, so network properties can be checked
in isolation. Values are standard-normal, not physically plausible.
"""

from __future__ import annotations

import numpy as np

from diacc.envs.observation import (
    CRITIC_NODE_FEATURES,
    LANE_FEATURES,
    MAX_LANES,
    MAX_SEGMENTS,
    N_ACTIONS,
    NODE_FEATURES,
    ROAD_FEATURES_PER_SEGMENT,
    SELF_FEATURES,
    TRAFFIC_FEATURES,
    ActorObs,
    CriticState,
    ObservationSpec,
)


def _normal(rng: np.random.Generator, *shape: int) -> np.ndarray:
    return rng.standard_normal(shape).astype(np.float32)


def _first_k_mask(rng: np.random.Generator, batch: tuple[int, ...], k: int) -> np.ndarray:
    counts = rng.integers(0, k + 1, size=batch)  # (...,)
    return np.arange(k) < counts[..., None]  # (..., K)


def random_actor_obs(
    spec: ObservationSpec, batch: tuple[int, ...], rng: np.random.Generator
) -> ActorObs:
    """ActorObs with leading axes ``batch``; each CAV has 0..K HDV and 0..K CAV neighbours."""
    t, k = spec.history_steps, spec.n_neighbours
    hdv_mask = _first_k_mask(rng, batch, k)
    cav_mask = _first_k_mask(rng, batch, k)
    lane_mask = np.ones((*batch, spec.lane_slots), dtype=bool)
    lane_mask[..., 1:] = rng.random((*batch, spec.lane_slots - 1)) < 0.7
    return ActorObs(
        self_state=_normal(rng, *batch, SELF_FEATURES),
        ego_hist=_normal(rng, *batch, t, NODE_FEATURES),
        hdv_nodes=_normal(rng, *batch, k, t, NODE_FEATURES) * hdv_mask[..., None, None],
        hdv_mask=hdv_mask,
        cav_nodes=_normal(rng, *batch, k, t, NODE_FEATURES) * cav_mask[..., None, None],
        cav_mask=cav_mask,
        cav_prev_action=rng.integers(0, N_ACTIONS, size=(*batch, k)) * cav_mask,
        lane_stats=_normal(rng, *batch, spec.lane_slots, LANE_FEATURES) * lane_mask[..., None],
        lane_mask=lane_mask,
        road=_normal(rng, *batch, ROAD_FEATURES_PER_SEGMENT * MAX_SEGMENTS),
        action_memory=rng.integers(0, N_ACTIONS, size=(*batch, 2)),
        action_mask=np.ones((*batch, N_ACTIONS), bool),
        alive=rng.random(batch) < 0.9,
    )


def random_critic_state(
    spec: ObservationSpec, batch: tuple[int, ...], rng: np.random.Generator, min_active: int = 1
) -> CriticState:
    """CriticState with leading axes ``batch``; ``min_active``..N vehicles in the first slots.

    Each active vehicle's neighbours are K distinct other active vehicles in
    random order (fewer, and masked, when the road holds fewer).
    """
    n, k = spec.max_vehicles, spec.n_neighbours
    active = rng.integers(min_active, n + 1, size=batch)  # (...,)
    node_mask = np.arange(n) < active[..., None]  # (..., N)
    # Random ranking of candidate neighbours; self and inactive vehicles sort last.
    keys = rng.random((*batch, n, n))  # (..., N, N)
    keys = np.where(node_mask[..., None, :], keys, np.inf)
    keys = np.where(np.eye(n, dtype=bool), np.inf, keys)
    order = np.argsort(keys, axis=-1)[..., :k]  # (..., N, K)
    n_candidates = np.maximum(active - 1, 0)[..., None, None]  # (..., 1, 1)
    neighbour_mask = (np.arange(k) < n_candidates) & node_mask[..., None]  # (..., N, K)
    lane_mask = np.arange(MAX_LANES) < rng.integers(1, MAX_LANES + 1, size=batch)[..., None]
    return CriticState(
        nodes=_normal(rng, *batch, n, CRITIC_NODE_FEATURES) * node_mask[..., None],
        node_mask=node_mask,
        neighbours=np.where(neighbour_mask, order, 0).astype(np.int64),
        neighbour_mask=neighbour_mask,
        lane_stats=_normal(rng, *batch, MAX_LANES, LANE_FEATURES) * lane_mask[..., None],
        lane_mask=lane_mask,
        road=_normal(rng, *batch, ROAD_FEATURES_PER_SEGMENT * MAX_SEGMENTS),
        traffic=_normal(rng, *batch, TRAFFIC_FEATURES),
    )
