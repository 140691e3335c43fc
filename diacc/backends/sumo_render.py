"""A plain NumPy top-down frame of a :class:`TrafficState` (for GIFs and debugging).

Drawn straight into an RGB array, so it needs no display and no SDL: the
road's lanes in grey, lane markings in white, HDVs in grey-blue shades by
style, CAVs in orange, collided vehicles in red. The whole route is squeezed
into ``width_px``; lateral scale is exaggerated so lanes stay readable.
"""

from __future__ import annotations

import numpy as np

from diacc.maps import Map
from diacc.state import TrafficState

_ROAD = np.array([90, 90, 90], np.uint8)
_GRASS = np.array([60, 110, 60], np.uint8)
_MARK = np.array([230, 230, 230], np.uint8)
_CAV = np.array([255, 140, 0], np.uint8)
_CRASH = np.array([220, 20, 20], np.uint8)
_HDV = np.array([[70, 130, 220], [150, 170, 200], [200, 210, 230]], np.uint8)  # by style


def render_topdown(
    road: Map, state: TrafficState, width_px: int = 1300, lane_px: int = 16
) -> np.ndarray:
    """RGB frame (H, W, 3) uint8 of the road and every active vehicle."""
    margin = lane_px
    height = road.max_lanes * lane_px + 2 * margin
    frame = np.empty((height, width_px, 3), np.uint8)
    frame[:] = _GRASS
    px_per_m = width_px / road.length_m
    exists = road.lane_exists()  # (S, L)
    for s, (x0, x1) in enumerate(zip(road.segment_starts_m, road.segment_ends_m, strict=True)):
        c0, c1 = int(x0 * px_per_m), int(np.ceil(x1 * px_per_m))
        for lane in np.flatnonzero(exists[s]):
            r1 = height - margin - lane * lane_px  # image rows grow downwards: lane 0 at bottom
            frame[r1 - lane_px : r1, c0:c1] = _ROAD
            frame[r1 - 1, c0:c1:8] = _MARK
    px_per_lat_m = lane_px / road.lane_width_m
    for i in np.flatnonzero(state.active):
        cx, cy = state.x_m[i] * px_per_m, height - margin - state.y_m[i] * px_per_lat_m
        half_l = max(1, int(0.5 * state.length_m[i] * px_per_m))
        half_w = max(1, int(0.5 * state.width_m[i] * px_per_lat_m))
        colour = _CAV if state.is_cav[i] else _HDV[max(int(state.style[i]), 0) % 3]
        if state.collided[i]:
            colour = _CRASH
        r0, r1 = int(cy) - half_w, int(cy) + half_w
        c0, c1 = int(cx) - half_l, int(cx) + half_l + 1
        frame[max(r0, 0) : max(r1, 0), max(c0, 0) : max(c1, 0)] = colour
    return frame
