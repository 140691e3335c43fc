"""Generated bottleneck maps: ordinary map descriptions drawn from one documented
distribution, reproducibly from a generator seed.

Four hand-written maps let a policy learn four roads; a distribution of roads lets
it be trained on some and tested on others it never saw. A generated map is plain
data, the same table a ``maps/*.toml`` file holds, validated by the same
:func:`~diacc.sim.maps.parse_map`, so every backend builds it as it builds the
shipped ones.

The distribution (:data:`DISTRIBUTION`, docs/concepts/maps.md): 2-5 lanes; one or
two reductions, each closing 1 or 2 lanes (never all) on the map's ``drop_side``,
left or right; the full width between and after them; segment lengths in 10 m steps;
the route's speed limit 20-33 m/s, each reduction's at most that. The first segment
is at least 400 m long, so that a release of up to 49 vehicles at the default 8 m
spacing fits in it.

Generator seeds are split into three streams by construction, like the episode seed
streams (:data:`diacc.experiments.grid.SEED_STREAMS`): stream ``k`` of
:data:`MAP_STREAMS` owns the seeds ``[k * STREAM_SEEDS, (k + 1) * STREAM_SEEDS)``, so
no test map is ever a training or validation map. Map ``index`` of a stream is named
``gen-<stream>-<index>`` (``gen-test-7``); :func:`~diacc.sim.maps.load_map`, and so
every ``--map`` option, accepts that name.

Draws use :class:`numpy.random.SeedSequence` words only (no Generator method, whose
streams numpy may change between versions), so a seed gives the same map on every
machine and numpy version.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

import numpy as np

from diacc.errors import MapError

#: Generator seed streams, in the order their seed ranges follow one another.
MAP_STREAMS = ("train", "validation", "test")
#: Seeds (maps) in each stream: stream k owns [k * STREAM_SEEDS, (k + 1) * STREAM_SEEDS).
STREAM_SEEDS = 1_000_000
#: Every generated map's name starts with this (``gen-test-7``).
NAME_PREFIX = "gen-"
#: First entropy word of every generator seed's draws (no other seeded stream uses it).
_GENERATOR_TAG = 0x3A9_6E4D
#: Words drawn per map: more than the most draws a map takes (a fixed count keeps
#: the words of a seed independent of how many draws its map needs).
_WORDS = 16


@dataclass(frozen=True)
class Distribution:
    """The ranges a generated map is drawn from; every range is inclusive, uniform.

    Lengths are drawn in steps of ``length_step_m``, speed limits in whole m/s.
    """

    lanes: tuple[int, int] = (2, 5)  # lanes of the full width
    reductions: tuple[int, int] = (1, 2)  # lane reductions along the route
    dropped_lanes: tuple[int, int] = (1, 2)  # lanes each reduction closes (fewer than all)
    approach_m: tuple[int, int] = (400, 900)  # first segment (the release starts there)
    reduction_m: tuple[int, int] = (200, 400)  # each reduction segment
    between_m: tuple[int, int] = (200, 500)  # full width between two reductions
    exit_m: tuple[int, int] = (150, 500)  # last segment, after the last reduction
    route_speed_mps: tuple[int, int] = (20, 33)  # full-width segments
    reduction_speed_min_mps: int = 20  # a reduction's limit: [this, the route's]
    length_step_m: int = 10
    lane_width_m: float = 3.2
    #: Share of lanes closed below which a reduction is labelled ``reduction25``
    #: (1 of 5, 4 or 3 lanes), ``reduction50`` from here (2 of 5, 2 of 4, 1 of 2, 2 of 3).
    reduction25_below: float = 0.375


#: The one distribution of generated maps (a new one gets new names, not new maps
#: under old names).
DISTRIBUTION = Distribution()


def generator_seed(stream: str, index: int) -> int:
    """Seed of map ``index`` of a generator stream; one-line :class:`MapError` if out of range."""
    if stream not in MAP_STREAMS:
        raise MapError(f"unknown map stream {stream!r}; use {', '.join(MAP_STREAMS)}")
    if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < STREAM_SEEDS:
        raise MapError(f"map index must be an integer in [0, {STREAM_SEEDS - 1}], got {index!r}")
    return MAP_STREAMS.index(stream) * STREAM_SEEDS + index


def seed_stream(seed: int) -> tuple[str, int]:
    """(stream, index) of a generator seed: the inverse of :func:`generator_seed`."""
    total = len(MAP_STREAMS) * STREAM_SEEDS
    if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < total:
        raise MapError(f"generator seed must be an integer in [0, {total - 1}], got {seed!r}")
    return MAP_STREAMS[seed // STREAM_SEEDS], seed % STREAM_SEEDS


def generated_name(stream: str, index: int) -> str:
    """Name of map ``index`` of a stream, e.g. ``gen-test-7`` (checked)."""
    generator_seed(stream, index)
    return f"{NAME_PREFIX}{stream}-{index}"


def generated_names(stream: str, count: int, start: int = 0) -> list[str]:
    """Names of maps ``start .. start + count - 1`` of a stream: what a suite of generated
    maps (the test stream's) or a training run across maps (the train stream's) lists."""
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise MapError(f"a count of generated maps must be an integer >= 1, got {count!r}")
    generated_name(stream, start + count - 1)  # the last index is in the stream
    return [generated_name(stream, index) for index in range(start, start + count)]


def is_generated_name(name: str) -> bool:
    """Whether ``name`` claims to be a generated map (it may still be malformed)."""
    return name.startswith(NAME_PREFIX)


def parse_generated_name(name: str) -> tuple[str, int]:
    """(stream, index) of ``gen-<stream>-<index>``; one-line :class:`MapError` if malformed."""
    stream, _, index = name.removeprefix(NAME_PREFIX).rpartition("-")
    form = f"generated maps are named {NAME_PREFIX}<{'|'.join(MAP_STREAMS)}>-<index>"
    if stream not in MAP_STREAMS or not index.isdigit() or index != str(int(index)):
        raise MapError(f"unknown map {name!r}; {form}")
    if int(index) >= STREAM_SEEDS:
        raise MapError(f"unknown map {name!r}; a stream's indices are 0-{STREAM_SEEDS - 1}")
    return stream, int(index)


class _Draws:
    """Uniform integers from a seed's SeedSequence words, one word per draw."""

    def __init__(self, seed: int) -> None:
        words = np.random.SeedSequence([_GENERATOR_TAG, seed]).generate_state(_WORDS)
        self._words = [int(w) for w in words]

    def integer(self, low: int, high: int) -> int:
        """An integer in [low, high] (bias below (high - low + 1) / 2**32)."""
        return low + self._words.pop(0) % (high - low + 1)

    def length_m(self, bounds: tuple[int, int], step_m: int) -> int:
        return step_m * self.integer(bounds[0] // step_m, bounds[1] // step_m)


def map_data(seed: int) -> dict:
    """The map description of a generator seed, as the table a map TOML file holds."""
    stream, index = seed_stream(seed)
    dist = DISTRIBUTION
    draw = _Draws(seed)
    lanes = draw.integer(*dist.lanes)
    n_reductions = draw.integer(*dist.reductions)
    drop_side = ("left", "right")[draw.integer(0, 1)]
    route_speed_mps = float(draw.integer(*dist.route_speed_mps))
    step = dist.length_step_m

    def full(length_m: int) -> dict:
        return _segment("multilane", length_m, lanes, route_speed_mps)

    segments = [full(draw.length_m(dist.approach_m, step))]
    for r in range(n_reductions):
        if r:
            segments.append(full(draw.length_m(dist.between_m, step)))
        dropped = draw.integer(dist.dropped_lanes[0], min(dist.dropped_lanes[1], lanes - 1))
        kind = "reduction25" if dropped / lanes < dist.reduction25_below else "reduction50"
        length_m = draw.length_m(dist.reduction_m, step)
        speed = float(draw.integer(dist.reduction_speed_min_mps, int(route_speed_mps)))
        segments.append(_segment(kind, length_m, lanes - dropped, speed))
    segments.append(full(draw.length_m(dist.exit_m, step)))
    return {
        "name": f"{NAME_PREFIX}{stream}-{index}",
        "description": _describe(seed, lanes, segments),
        "lane_width_m": dist.lane_width_m,
        "drop_side": drop_side,
        "segments": segments,
    }


def _segment(kind: str, length_m: int, lanes: int, speed_limit_mps: float) -> dict:
    return {"kind": kind, "length_m": length_m, "lanes": lanes, "speed_limit_mps": speed_limit_mps}


def _describe(seed: int, lanes: int, segments: list[dict]) -> str:
    """One line a reader can check the segments against (as the shipped maps have)."""
    x_m, parts = 0, []
    for seg in segments:
        if seg["kind"] != "multilane":
            parts.append(
                f"{lanes} -> {seg['lanes']} lanes at {x_m}-{x_m + seg['length_m']} m "
                f"({seg['speed_limit_mps']:g} m/s)"
            )
        x_m += seg["length_m"]
    limit = segments[0]["speed_limit_mps"]
    return f"Generated (seed {seed}), {x_m} m, {limit:g} m/s: " + ", ".join(parts)


def map_toml(seed: int) -> str:
    """The TOML text of a generator seed's map, laid out like ``maps/*.toml``.

    Loading the text gives the same :class:`~diacc.sim.maps.Map` as the name does,
    so a generated map can be saved, edited and passed as a file.
    """
    data = map_data(seed)
    lines = [
        f"# {data['description']}",
        "# Generated by diacc.sim.mapgen; plain data: read by diacc.sim.maps.load_map().",
        f"name = {_string(data['name'])}",
        f"description = {_string(data['description'])}",
        f"lane_width_m = {data['lane_width_m']}",
        f"drop_side = {_string(data['drop_side'])}",
    ]
    for seg in data["segments"]:
        lines += ["", "[[segments]]"]
        lines += [f"{key} = {_value(value)}" for key, value in seg.items()]
    return "\n".join(lines) + "\n"


def _string(text: str) -> str:
    """A TOML basic string (JSON's escaping of ASCII text is valid TOML)."""
    return json.dumps(text, ensure_ascii=True)


def _value(value: str | int | float) -> str:
    return _string(value) if isinstance(value, str) else repr(value)
