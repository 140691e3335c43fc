"""What the features of one instant read: the state, its history and its neighbour sets."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from diacc.records import Batched, per_env
from diacc.sim.state import TrafficState, on_road_window, take_last


@dataclass
class History(Batched):
    """The last T states' per-vehicle fields of E envs, oldest first (a
    :class:`~diacc.records.Batched` record: ``rows`` selects envs)."""

    x_m: np.ndarray = per_env("E, T, V")
    y_m: np.ndarray = per_env("E, T, V")
    speed_mps: np.ndarray = per_env("E, T, V")
    heading_rad: np.ndarray = per_env("E, T, V")
    active: np.ndarray = per_env("E, T, V")

    @classmethod
    def filled(cls, state: TrafficState, steps: int) -> History:
        """T copies of ``state``."""
        return cls(
            *(np.repeat(getattr(state, f.name)[..., None, :], steps, axis=-2) for f in fields(cls))
        )

    def fill_rows(self, rows: np.ndarray, state: TrafficState) -> None:
        """Envs ``rows`` of a batch history start afresh: T copies of their ``state`` rows."""
        for f in fields(self):
            getattr(self, f.name)[rows] = getattr(state, f.name)[rows, None, :]

    def push(self, state: TrafficState) -> None:
        for f in fields(self):
            arr = getattr(self, f.name)  # (..., T, V)
            arr[..., :-1, :] = arr[..., 1:, :]
            arr[..., -1, :] = getattr(state, f.name)


@dataclass
class Frame:
    """What the observations of one instant are built from: the state, its history
    and its neighbour sets; every array with the state's leading (env) axes.

    The neighbour sets are searched when first needed (None until then), so
    that a batch's are searched in one call.
    """

    state: TrafficState
    hist: History  # fields (..., T, V)
    nbr: np.ndarray | None = None  # (..., V, K) int64
    nbr_mask: np.ndarray | None = None  # (..., V, K) bool

    def searched(self, n_neighbours: int) -> Frame:
        """This frame, with its neighbour sets searched if they were not yet."""
        if self.nbr is None:
            self.nbr, self.nbr_mask = nearest_neighbours(self.state, n_neighbours)
        return self


def nearest_neighbours(state: TrafficState, k: int) -> tuple[np.ndarray, np.ndarray]:
    """K nearest active vehicles in same/adjacent lanes for every vehicle, (..., V, K) each.

    The neighbour rule of the layout (:mod:`diacc.envs.observation.layout`): by
    ``|x_j - x_i|``, ties to the lower index; one (W, W) distance table serves the
    actor's and the critic's sets alike. Searched within
    :func:`~diacc.sim.state.on_road_window` alone (vehicles off the road have no
    neighbours and are none): the table scales with the vehicles on the road, not with
    a demand episode's V.
    """
    lo, hi = on_road_window(state.active)
    part = state if hi - lo == state.n_vehicles else state.vehicles(lo, hi)
    n_win = hi - lo
    x, lane, act = part.x_m, part.lane.astype(np.int64), part.active
    i_, j_ = (Ellipsis, slice(None), None), (Ellipsis, None, slice(None))  # [..., i, j]
    dist = np.abs(x[j_] - x[i_])  # (..., W, W) ego i, other j
    ok = (np.abs(lane[j_] - lane[i_]) <= 1) & act[j_] & act[i_] & ~np.eye(n_win, dtype=bool)
    dist = np.where(ok, dist, np.inf)
    if n_win < k:  # fewer candidates than slots: pad with never-chosen columns
        pad = [(0, 0)] * (dist.ndim - 1) + [(0, k - n_win)]
        dist = np.pad(dist, pad, constant_values=np.inf)
    order = np.argsort(dist, axis=-1, kind="stable")[..., :k]  # (..., W, K)
    nbr = np.zeros(state.x_m.shape + (k,), np.int64)  # (..., V, K)
    mask = np.zeros(state.x_m.shape + (k,), bool)
    mask[..., lo:hi, :] = np.isfinite(take_last(dist, order))
    nbr[..., lo:hi, :] = np.where(mask[..., lo:hi, :], lo + order, 0)
    return nbr, mask
