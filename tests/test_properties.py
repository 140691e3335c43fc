"""Property-based tests (hypothesis): any map file, grid file or ``--set`` override gives a
valid object or a one-line :class:`~diacc.errors.DiaccError`, in bounded time.

The hand-written fault table (tests/test_faults.py) lists the inputs someone
thought of; these generate the others (issue 22 found nested arrays,
non-table segments, products of long lists and 60,000-segment maps this way).
``deadline`` bounds each example's time.
"""

from __future__ import annotations

import dataclasses
import math
import tempfile
from pathlib import Path

from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from diacc.config import TrainConfig, _leaves, override, validate
from diacc.errors import DiaccError
from diacc.experiments.grid import Cell, load_grid
from diacc.sim.maps import Map, load_map

SETTINGS = settings(
    max_examples=60, deadline=2000, suppress_health_check=[HealthCheck.too_slow], derandomize=True
)

# TOML-representable values, nested a little.
scalars = st.one_of(
    st.booleans(),
    st.integers(min_value=-(2**63), max_value=2**63 - 1),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
)
values = st.recursive(
    scalars,
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4)
    ),
    max_leaves=12,
)


def _toml_value(value) -> str:
    """``value`` written as TOML (inline tables and arrays)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        return ("inf" if value > 0 else "-inf") if math.isinf(value) else repr(value)
    if isinstance(value, str):
        return '"' + "".join(c if c.isprintable() and c not in '"\\' else "?" for c in value) + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return "{" + ", ".join(f"{_toml_value(k)} = {_toml_value(v)}" for k, v in value.items()) + "}"


def _toml(table: dict) -> str:
    return "".join(f"{_toml_value(k)} = {_toml_value(v)}\n" for k, v in table.items())


def _load(loader, text: str | bytes):
    """``loader(file holding text)``: its result, or the DiaccError it raised (one line)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "input.toml"
        path.write_bytes(text if isinstance(text, bytes) else text.encode())
        try:
            return loader(path)
        except DiaccError as exc:
            assert str(exc) and "\n" not in str(exc), repr(exc)
            return exc


# ----------------------------------------------------------------------------- maps
segment = st.fixed_dictionaries(
    {},
    optional={
        "kind": st.sampled_from(["multilane", "reduction25", "reduction50"]) | values,
        "length_m": st.floats(min_value=1e-3, max_value=1e4) | values,
        "lanes": st.integers(min_value=-2, max_value=20) | values,
        "speed_limit_mps": st.floats(min_value=0, max_value=80) | values,
        "extra": values,
    },
)
map_table = st.fixed_dictionaries(
    {"segments": st.lists(segment | values, max_size=6) | values},
    optional={
        "name": st.text(max_size=10) | values,
        "lane_width_m": st.floats(min_value=1, max_value=6) | values,
        "drop_side": st.sampled_from(["left", "right", "up"]) | values,
        "description": values,
    },
)


@SETTINGS
@given(map_table)
@example({"name": "x", "lane_width_m": 3.2, "segments": [1]})  # a segment that is not a table
@example({"name": "x", "lane_width_m": 3.2, "segments": [{"kind": "multilane", "length_m": 9.0,
          "lanes": 40_000_000, "speed_limit_mps": 20.0}]})  # fmt: skip
def test_any_map_table_gives_a_map_or_one_line(table):
    result = _load(load_map, _toml(table))
    if isinstance(result, Map):
        ends = result.lane_end_m()  # (S, L)
        assert ends.shape == (len(result.segments), result.max_lanes)
        assert (ends[result.lane_exists()] > result.segment_starts_m.repeat(result.max_lanes)
                .reshape(ends.shape)[result.lane_exists()]).all()  # fmt: skip


@SETTINGS
@given(st.binary(max_size=200) | st.text(max_size=200))
def test_any_bytes_as_a_map_file_give_a_map_or_one_line(raw):
    _load(load_map, raw)


# ----------------------------------------------------------------------------- grids
cell = st.fixed_dictionaries(
    {},
    optional={
        "map": st.sampled_from(["train-25", "test-50", "nowhere"]) | values,
        "n_vehicles": st.integers(min_value=-1, max_value=60) | values,
        "cav_penetration": st.floats(min_value=-0.5, max_value=1.5) | values,
        "style_mix": st.sampled_from(["D1", "D2", "D9"]) | values,
        "lanes": values,
    },
)
grid_table = st.fixed_dictionaries(
    {},
    optional={
        "cells": st.lists(cell | values, max_size=4) | values,
        "product": st.dictionaries(
            st.sampled_from(["map", "n_vehicles", "cav_penetration", "style_mix", "x"]),
            st.lists(values, max_size=300) | values,
        )
        | values,
        "other": values,
    },
)


@SETTINGS
@given(grid_table)
def test_any_grid_file_gives_cells_or_one_line(table):
    # A table of arrays of tables is written as inline tables: TOML allows both.
    result = _load(load_grid, _toml(table))
    if not isinstance(result, DiaccError):
        assert result and all(isinstance(c, Cell) for c in result)
        assert all("/" not in c.file_key for c in result)


# ----------------------------------------------------------------------------- --set
KEYS = [key for key, _ in _leaves(TrainConfig())]
SECTIONS = sorted(
    {key.rsplit(".", 1)[0] for key in KEYS if "." in key} | {"env", "nope", "env.sim.cav.x.y"}
)


@SETTINGS
@given(
    st.dictionaries(
        st.sampled_from(KEYS + SECTIONS) | st.text(max_size=10),
        st.text(max_size=12) | st.sampled_from(["nan", "-1", "1e400", "true", "0", "3"]),
        max_size=4,
    )
)
def test_any_set_override_gives_a_valid_config_or_one_line(overrides):
    try:
        cfg = validate(override(TrainConfig(), overrides))
    except DiaccError as exc:
        assert str(exc) and "\n" not in str(exc)
        return
    for key, value in _leaves(cfg):  # every leaf keeps its declared type
        default = dict(_leaves(TrainConfig()))[key]
        assert type(value) is type(default), (key, value)
    assert dataclasses.is_dataclass(cfg.env.sim)
