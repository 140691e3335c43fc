"""What the features read of the map: normalisation scales and static tables, computed once."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from diacc.envs.observation.layout import MAX_LANES, MAX_SEGMENTS, ROAD_FEATURES_PER_SEGMENT
from diacc.sim.maps import Map

#: The road table's fourth column for each segment present (the layout's ``road``).
SegmentColumn = Callable[[Map], "list[float] | float"]


def segment_present(road: Map) -> float:
    """1 for every segment present (the paper's observation)."""
    return 1.0


def segment_speed_limit(road: Map) -> list[float]:
    """Each segment's speed limit / the route's highest (``road_speed_limits``), so that
    actor and critic see the limits a preset lowers (``paper-congestion``)."""
    return [seg.speed_limit_mps / road.max_speed_mps for seg in road.segments]


@dataclass(frozen=True)
class MapScales:
    """The map's scales and static tables, in the agents' frame (a mirrored map if so)."""

    road: Map
    route_m: float  # x scale
    v_max_mps: float  # speed scale
    lane_w_m: float  # dy scale
    road_w_m: float  # y scale
    lane_norm: float  # lane index scale: max_lanes - 1 (at least 1)
    exists_pad: np.ndarray  # (S, Lm + 2) lane exists; a False column each side (lanes -1, Lm)
    lane_end_m: np.ndarray  # (S, Lm) where each lane ends (inf: it does not)
    lane_len_km: np.ndarray  # (MAX_LANES,) length on which each lane exists
    road_table: np.ndarray  # (4 MAX_SEGMENTS,) float32 the layout's road table

    @classmethod
    def of(cls, road: Map, segment_column: SegmentColumn) -> MapScales:
        route_m = road.length_m
        exists = road.lane_exists()  # (S, Lm)
        seg_len_m = np.array([s.length_m for s in road.segments])  # (S,)
        lane_len_km = np.zeros(MAX_LANES)
        lane_len_km[: road.max_lanes] = (exists * seg_len_m[:, None]).sum(axis=0) / 1000.0
        table = np.zeros((MAX_SEGMENTS, ROAD_FEATURES_PER_SEGMENT), np.float32)  # (S_max, 4)
        n_seg = len(road.segments)
        table[:n_seg, 0] = road.segment_starts_m / route_m
        table[:n_seg, 1] = road.segment_ends_m / route_m
        table[:n_seg, 2] = [s.lanes / road.max_lanes for s in road.segments]
        table[:n_seg, 3] = segment_column(road)
        return cls(
            road=road,
            route_m=route_m,
            v_max_mps=road.max_speed_mps,
            lane_w_m=road.lane_width_m,
            road_w_m=road.max_lanes * road.lane_width_m,
            lane_norm=float(max(road.max_lanes - 1, 1)),
            exists_pad=np.pad(exists, ((0, 0), (1, 1)), constant_values=False),
            lane_end_m=road.lane_end_m(),
            lane_len_km=lane_len_km,
            road_table=table.reshape(-1),
        )
