"""Road geometry of the highway backend: a highway-env RoadNetwork plus lane tables.

Two frames meet here. diacc numbers lanes from the *right* (absolute lane 0
is the rightmost lane of the widest cross-section) with ``y`` growing to the
left; highway-env numbers lanes from the *left* (its lane index 0 has the
smallest screen ``y``, and screen ``y`` grows downwards). The mapping is

    y_highway_env = road_width_m - y_diacc,
    highway_env_lane = max_lanes - 1 - absolute_lane   (full cross-section)

and it lives only in this module and the renderer, so the dynamics never see
highway-env's convention.

The dynamics only need small lookup tables (segment x lane), precomputed once
per map in :class:`LaneTables`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from highway_env.road.lane import LineType, StraightLane
from highway_env.road.road import RoadNetwork

from diacc.sim.maps import Map


def road_width_m(road: Map) -> float:
    """Width of the widest cross-section: the flip axis between the two frames."""
    return road.max_lanes * road.lane_width_m


def to_highway_env_y(road: Map, y_m: np.ndarray | float) -> np.ndarray:
    """diacc lateral position (left of right edge) -> highway-env y (down the screen)."""
    return road_width_m(road) - np.asarray(y_m, dtype=np.float64)


def to_highway_env_lane(road: Map, lane: int) -> int:
    """Absolute diacc lane -> highway-env lane index of the full cross-section."""
    return road.max_lanes - 1 - int(lane)


def build_road_network(road: Map) -> RoadNetwork:
    """highway-env ``RoadNetwork`` of a map: one edge per segment, one lane per existing lane.

    Nodes are ``"s0" .. "sS"`` at segment boundaries. Within an edge the lanes
    are added in highway-env order (leftmost first), each a ``StraightLane``
    with continuous lines on the outer road edges and striped lines between
    lanes, so that the stock renderer draws the bottleneck as it is.
    """
    network = RoadNetwork()
    starts, ends = road.segment_starts_m, road.segment_ends_m
    width = road.lane_width_m
    for s, segment in enumerate(road.segments):
        lanes = list(road.lane_range(s))
        leftmost, rightmost = max(lanes), min(lanes)
        for lane in sorted(lanes, reverse=True):  # leftmost (highway-env index 0) first
            y_he = float(to_highway_env_y(road, road.lane_center_y_m(lane)))
            left_line = LineType.CONTINUOUS_LINE if lane == leftmost else LineType.STRIPED
            right_line = LineType.CONTINUOUS_LINE if lane == rightmost else LineType.NONE
            network.add_lane(
                f"s{s}",
                f"s{s + 1}",
                StraightLane(
                    [float(starts[s]), y_he],
                    [float(ends[s]), y_he],
                    width=width,
                    line_types=(left_line, right_line),
                    speed_limit=segment.speed_limit_mps,
                ),
            )
    return network


@dataclass(frozen=True)
class LaneTables:
    """Per (segment, absolute lane) facts the vectorised dynamics index into.

    Attributes:
        exists: (S, L) bool, lane present in segment.
        end_m: (S, L) float, x where the lane (driven from segment s) stops
            existing; ``inf`` if it never does (see ``Map.lane_end_m``).
        merge_dir: (S, L) int8, lane step (-1 right / +1 left / 0 none) that a
            vehicle in a lane that ends must take towards a lane that
            continues further.
        speed_limit_mps: (S,) float.
        segment_ends_m: (S,) float, for ``np.searchsorted``.
    """

    exists: np.ndarray
    end_m: np.ndarray
    merge_dir: np.ndarray
    speed_limit_mps: np.ndarray
    segment_ends_m: np.ndarray

    @classmethod
    def from_map(cls, road: Map) -> LaneTables:
        exists = road.lane_exists()
        end_m = road.lane_end_m()
        n_seg, n_lanes = exists.shape
        merge_dir = np.zeros((n_seg, n_lanes), dtype=np.int8)
        for s in range(n_seg):  # setup only: S x L is tiny
            for lane in range(n_lanes):
                if not exists[s, lane] or not np.isfinite(end_m[s, lane]):
                    continue
                better = [
                    m for m in range(n_lanes) if exists[s, m] and end_m[s, m] > end_m[s, lane]
                ]
                if better:
                    nearest = min(better, key=lambda m: (abs(m - lane), m))
                    merge_dir[s, lane] = np.sign(nearest - lane)
        return cls(
            exists=exists,
            end_m=end_m,
            merge_dir=merge_dir,
            speed_limit_mps=road.speed_limits_mps(),
            segment_ends_m=road.segment_ends_m,
        )

    def segment_of(self, x_m: np.ndarray) -> np.ndarray:
        """(V,) segment index of each position, clipped to the route."""
        idx = np.searchsorted(self.segment_ends_m, x_m, side="right")
        return np.minimum(idx, len(self.segment_ends_m) - 1)
