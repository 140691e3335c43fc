"""Map descriptions: one plain-data file drives every backend.

A map is a straight route cut into consecutive segments. Each segment has a
length, a number of lanes and a speed limit, and a *kind* label
(``multilane``, ``reduction25``, ``reduction50``) so that metrics can be
reported per kind of road. Lanes are numbered in one absolute frame for the
whole route: lane 0 is the rightmost lane of the widest cross-section. When a
segment has fewer lanes, the missing ones are on ``drop_side``: with
``drop_side = "left"`` a 3-lane segment of a 4-lane route keeps lanes 0..2,
with ``"right"`` it keeps lanes 1..3. Keeping one absolute numbering lets the
observation builder compare lanes across segments without knowing the
backend.

Files are TOML (see ``maps/*.toml``, shipped as package data: :data:`MAPS_DIR`).
Every rule is checked on load and a broken file raises :class:`MapError` with a
one-line message naming the file and the field.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from diacc.errors import MapError
from diacc.shipped import data_dir, require_dir
from diacc.sim import mapgen
from diacc.tomlfile import read_toml

#: Folder with the shipped map descriptions: package data (:mod:`diacc.shipped`), in a
#: clone a link to ``maps/`` at the repository root.
MAPS_DIR = data_dir("maps")

SEGMENT_KINDS = ("multilane", "reduction25", "reduction50")
DROP_SIDES = ("left", "right")
#: The largest change in lane count allowed between two consecutive segments.
MAX_LANE_JUMP = 2
#: Most lanes of a segment (per-lane tables are (segments, lanes): a typo such as
#: ``lanes = 40000000`` must be an error, not an out-of-memory).
MAX_LANES = 16

_TOP_KEYS = {"name", "description", "lane_width_m", "drop_side", "segments"}
#: Shortest segment (m): shorter ones hold no vehicle, and the simulators divide by
#: their length (highway-env warned of division by zero at 1e-300 m).
MIN_SEGMENT_M = 1.0
_SEGMENT_KEYS = {"kind", "length_m", "lanes", "speed_limit_mps"}


@dataclass(frozen=True)
class Segment:
    """One stretch of road with a constant cross-section."""

    kind: str
    length_m: float
    lanes: int
    speed_limit_mps: float


@dataclass(frozen=True)
class Map:
    """A validated map description (see module docstring for conventions)."""

    name: str
    description: str
    lane_width_m: float
    drop_side: str
    segments: tuple[Segment, ...]

    # ---- derived geometry -------------------------------------------------
    @property
    def length_m(self) -> float:
        return float(sum(s.length_m for s in self.segments))

    @property
    def max_lanes(self) -> int:
        return max(s.lanes for s in self.segments)

    @property
    def max_speed_mps(self) -> float:
        return max(s.speed_limit_mps for s in self.segments)

    @property
    def segment_starts_m(self) -> np.ndarray:
        """(S,) x where each segment starts."""
        return np.concatenate([[0.0], np.cumsum([s.length_m for s in self.segments])[:-1]])

    @property
    def segment_ends_m(self) -> np.ndarray:
        """(S,) x where each segment ends."""
        return np.cumsum([s.length_m for s in self.segments]).astype(float)

    def first_lane(self, segment_index: int) -> int:
        """Absolute index of the rightmost lane that exists in a segment."""
        lanes = self.segments[segment_index].lanes
        return 0 if self.drop_side == "left" else self.max_lanes - lanes

    def lane_range(self, segment_index: int) -> range:
        """Absolute lane indices present in a segment."""
        first = self.first_lane(segment_index)
        return range(first, first + self.segments[segment_index].lanes)

    def lane_exists(self) -> np.ndarray:
        """(S, L) bool: whether absolute lane l exists in segment s (read-only, cached)."""
        return _cached(self, "_exists", self._compute_lane_exists)

    def _compute_lane_exists(self) -> np.ndarray:
        table = np.zeros((len(self.segments), self.max_lanes), dtype=bool)
        for s in range(len(self.segments)):
            table[s, list(self.lane_range(s))] = True
        return table

    def lane_end_m(self) -> np.ndarray:
        """(S, L) x where lane l, driven from segment s, stops existing (inf if never).

        This is what forced-merge rules look at: a vehicle in lane l inside
        segment s must leave the lane before this point. Read-only, cached
        (PSAR reads it every step).
        """
        return _cached(self, "_ends", self._compute_lane_end_m)

    def _compute_lane_end_m(self) -> np.ndarray:
        # One backward sweep over segments, O(S * L): a lane that exists in
        # segment s ends where it ends from s + 1; one that does not ends at
        # s's start. (A search forward from every segment was quadratic: a
        # 60,000-segment map never loaded.)
        exists = self.lane_exists()  # (S, L)
        starts = self.segment_starts_m  # (S,)
        out = np.full(exists.shape, np.inf)  # (S, L)
        later = np.full(exists.shape[1], np.inf)  # (L,) the answer for segment s + 1
        for s in range(len(self.segments) - 1, -1, -1):
            later = np.where(exists[s], later, starts[s])
            out[s] = later
        return out

    def speed_limits_mps(self) -> np.ndarray:
        """(S,) each segment's speed limit (read-only, cached: read every step)."""
        return _cached(
            self, "_limits", lambda: np.array([s.speed_limit_mps for s in self.segments])
        )

    def exit_ends_m(self) -> tuple[np.ndarray, np.ndarray]:
        """(S, L) end of lane l seen from segment s (-inf where it does not exist there),
        and the later end of its two neighbours (-inf: none exists). Read-only, cached
        (PSAR's trapped-lane wall reads them every step)."""
        return _cached(self, "_own_ends", self._compute_own_ends), _cached(
            self, "_exit_ends", self._compute_exit_ends
        )

    def _compute_own_ends(self) -> np.ndarray:
        return np.where(self.lane_exists(), self.lane_end_m(), -np.inf)

    def _compute_exit_ends(self) -> np.ndarray:
        padded = np.pad(self._compute_own_ends(), [(0, 0), (1, 1)], constant_values=-np.inf)
        return np.maximum(padded[:, 2:], padded[:, :-2])  # (S, L) max(lane + 1, lane - 1)

    def lane_change_allowed(
        self,
        segment: np.ndarray,
        lane: np.ndarray,
        offset: np.ndarray,
        x_m: np.ndarray,
        reach_m: np.ndarray,
    ) -> np.ndarray:
        """Whether a change from ``lane`` by ``offset`` (+1 left, -1 right) can be made.

        The one rule that PSAR and both backends apply to a commanded lane
        change, so that no change PSAR approved is dropped by a simulator
        (and none is silently skipped): the target lane exists in the
        vehicle's ``segment`` and does not end within ``reach_m`` ahead of
        the vehicle's centre ``x_m`` (callers pass the distance covered during
        the change plus the vehicle length, see
        :func:`diacc.sim.kinematics.lane_change_reach_m`). ``offset == 0`` is not a
        lane change and gives False. Arrays broadcast; returns bool.
        """
        segment = np.asarray(segment, dtype=np.int64)
        target = np.asarray(lane, dtype=np.int64) + np.asarray(offset, dtype=np.int64)
        in_range = (target >= 0) & (target < self.max_lanes)
        target_c = np.minimum(np.maximum(target, 0), self.max_lanes - 1)
        exists = self.lane_exists()[segment, target_c]
        ends_later = self.lane_end_m()[segment, target_c] - np.asarray(x_m) > reach_m
        return (np.asarray(offset) != 0) & in_range & exists & ends_later

    def segment_of(self, x_m: np.ndarray) -> np.ndarray:
        """Segment index for each longitudinal position (clipped to the route)."""
        idx = np.searchsorted(self.segment_ends_m, x_m, side="right")
        return np.minimum(np.maximum(idx, 0), len(self.segments) - 1)

    def lane_center_y_m(self, lane: np.ndarray | int) -> np.ndarray:
        """Lateral coordinate of an absolute lane's centre line."""
        return (np.asarray(lane) + 0.5) * self.lane_width_m

    def content_hash(self) -> str:
        """Stable hash of the geometry (for caches such as SUMO networks)."""
        payload = json.dumps(asdict(self), sort_keys=True).encode()
        return hashlib.sha256(payload).hexdigest()[:16]


def _cached(road: Map, name: str, compute) -> np.ndarray:
    """Derived table stored on the frozen Map instance (computed once, read-only)."""
    table = road.__dict__.get(name)
    if table is None:
        table = compute()
        table.setflags(write=False)
        object.__setattr__(road, name, table)
    return table


def map_tag(name_or_path: str | Path) -> str:
    """A file-name-safe name of a map for run directories: identity by content.

    A shipped map keeps its name (``train-25``); a map file adds the hash of
    its content to its stem (``mymap-3f2a1b0c``), so that two files of one
    name in different folders, or one file edited between runs, never share
    a run directory.
    """
    path = Path(name_or_path)
    if path.suffix != ".toml":
        return _safe_name(str(name_or_path))
    try:
        digest = hashlib.sha256(path.read_bytes()).hexdigest()[:8]
    except OSError as exc:
        raise MapError(f"{path}: cannot read the map file ({exc.strerror})") from None
    return f"{_safe_name(path.stem)}-{digest}"


def _safe_name(text: str) -> str:
    """``text`` with all but letters, digits, ``-``, ``_`` and ``.`` replaced by ``_``."""
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in text).lstrip(".")
    return safe[:64] or "map"


def available_maps() -> list[str]:
    """Names of the shipped maps (:data:`MAPS_DIR`)."""
    return sorted(p.stem for p in require_dir("maps").glob("*.toml"))


def generate_map(stream: str, index: int) -> Map:
    """Map ``index`` of a generator stream (:mod:`diacc.sim.mapgen`), validated like
    any map file."""
    seed = mapgen.generator_seed(stream, index)
    return parse_map(mapgen.map_data(seed), source=mapgen.generated_name(stream, index))


def load_map(name_or_path: str | Path) -> Map:
    """Load a shipped map by name (``"train-25"``), a generated one by name
    (``"gen-test-7"``, :mod:`diacc.sim.mapgen`) or any TOML file by path."""
    path = Path(name_or_path)
    if path.suffix != ".toml":
        name = str(name_or_path)
        if mapgen.is_generated_name(name):
            return generate_map(*mapgen.parse_generated_name(name))
        path = require_dir("maps") / f"{name}.toml"
        if not path.exists():
            raise MapError(
                f"unknown map {name!r}; shipped maps: {', '.join(available_maps())}; "
                f"generated maps: {mapgen.NAME_PREFIX}<{'|'.join(mapgen.MAP_STREAMS)}>-<index>"
            )
    if not path.exists():
        raise MapError(f"{path}: map file not found")
    return parse_map(read_toml(path, MapError), source=str(path))


def _is_number(value) -> bool:
    """An int or float, not a bool (comparisons then reject NaN: ``nan <= x`` is False)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def parse_map(data: dict, source: str = "<map>") -> Map:
    """Validate a map dictionary (as read from TOML) into a :class:`Map`."""

    def fail(field: str, why: str) -> MapError:
        return MapError(f"{source}: field '{field}' {why}")

    if not isinstance(data, dict):
        raise MapError(f"{source}: a map must be a table, got {type(data).__name__}")
    unknown = set(data) - _TOP_KEYS
    if unknown:
        raise fail(sorted(unknown)[0], "is not a known key")
    for key in ("name", "description"):
        if key in data and not isinstance(data[key], str):
            raise fail(key, f"must be a string, got {data[key]!r}")
    for key in ("name", "lane_width_m", "segments"):
        if key not in data:
            raise fail(key, "is missing")
    width = data["lane_width_m"]
    if not _is_number(width) or not 2.0 <= width <= 5.0:
        raise fail("lane_width_m", f"must be a number in [2, 5] m, got {width!r}")
    drop_side = data.get("drop_side", "left")
    if not isinstance(drop_side, str) or drop_side not in DROP_SIDES:
        raise fail("drop_side", f"must be one of {DROP_SIDES}, got {drop_side!r}")
    raw_segments = data["segments"]
    if not isinstance(raw_segments, list) or not raw_segments:
        raise fail("segments", "must be a non-empty list of [[segments]] tables")

    segments: list[Segment] = []
    for i, seg in enumerate(raw_segments):
        where = f"segments[{i}]"
        if not isinstance(seg, dict):
            raise fail(where, f"must be a table of {', '.join(sorted(_SEGMENT_KEYS))}")
        unknown = set(seg) - _SEGMENT_KEYS
        if unknown:
            raise fail(f"{where}.{sorted(unknown)[0]}", "is not a known key")
        for key in sorted(_SEGMENT_KEYS):
            if key not in seg:
                raise fail(f"{where}.{key}", "is missing")
        if not isinstance(seg["kind"], str) or seg["kind"] not in SEGMENT_KINDS:
            raise fail(f"{where}.kind", f"must be one of {SEGMENT_KINDS}, got {seg['kind']!r}")
        length = seg["length_m"]
        if not _is_number(length) or not MIN_SEGMENT_M <= length < math.inf:
            shortest = f"must be a finite number >= {MIN_SEGMENT_M:g} m, got {length!r}"
            raise fail(f"{where}.length_m", shortest)
        lanes = seg["lanes"]
        if not isinstance(lanes, int) or isinstance(lanes, bool) or not 1 <= lanes <= MAX_LANES:
            raise fail(f"{where}.lanes", f"must be an integer in [1, {MAX_LANES}], got {lanes!r}")
        speed = seg["speed_limit_mps"]
        if not _is_number(speed) or not 0 < speed <= 70:
            raise fail(f"{where}.speed_limit_mps", f"must be in (0, 70] m/s, got {speed!r}")
        if segments and abs(lanes - segments[-1].lanes) > MAX_LANE_JUMP:
            raise fail(
                f"{where}.lanes",
                f"jumps from {segments[-1].lanes} to {lanes}; at most {MAX_LANE_JUMP} lanes "
                "may start or end between two segments",
            )
        segments.append(Segment(seg["kind"], float(length), lanes, float(speed)))

    return Map(
        name=str(data["name"]),
        description=str(data.get("description", "")),
        lane_width_m=float(width),
        drop_side=drop_side,
        segments=tuple(segments),
    )
