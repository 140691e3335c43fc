"""Checked settings: the one path every config section's values are checked by.

A field's range or choices are written next to it (:func:`ranged`, :func:`one_of`)
and :func:`check_fields` checks them, with every float finite, once, when the
section is built: in its ``__post_init__``. Every section uses it, the simulator's
(:mod:`diacc.sim.settings`, :class:`~diacc.sim.scenario.Scenario`) as well as the
environment's and the trainer's (:mod:`diacc.config`) and the evaluation's
(:class:`~diacc.experiments.policies.EvalSettings`), so code that reads a setting
never checks it again and every bad value is the same one-line
:class:`ConfigError`. A top-level module below every layer, so that the simulator's
settings need not import :mod:`diacc.config`.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import field
from typing import Any

from diacc.errors import DiaccError

# --------------------------------------------------------------------------
# Upper bounds of the size-like settings
# --------------------------------------------------------------------------
# Every count that sizes an array or a loop has an upper bound, so that a typo
# (``hidden_dim=1000000000``) is a one-line error before anything is allocated or
# written, not an allocator traceback or a hang. Each lies far above any setting
# the project uses and below what a 24 GiB, 2-core machine holds or finishes; the
# measurements behind them are in docs/guide/faults.md ("Every size has an upper
# bound").
#: Highway integration steps per decision: each one is a pass over every vehicle.
MAX_SUBSTEPS = 100
#: Decisions per episode (and per rollout, which holds whole episodes).
MAX_EPISODE_STEPS = 10_000
#: Observation neighbours K and history steps T: the actor's tables are (C, K, T).
MAX_NEIGHBOURS = 64
MAX_HISTORY_STEPS = 100
#: Width of any network layer: a 1024-wide learner already has ~44 M weights.
MAX_NETWORK_DIM = 1024
MAX_HEADS = 64
#: Environments of one run: every one adds a simulator and its rollout rows.
MAX_ENVS = 1024
#: PPO epochs over one rollout.
MAX_EPOCHS = 100
#: Bytes the rollout's observations may take (their upper estimate,
#: :func:`diacc.config.rollout_bytes`): a third of 24 GiB, as the update copies the
#: batch again.
MAX_ROLLOUT_BYTES = 8 * 2**30
#: Most vehicles of one scenario (a release's count, a demand's inflow x duration).
#: A step's pairwise checks (gaps, neighbours, PSAR) grow with the square of the
#: count (its step time and memory are in docs/guide/faults.md), and a typo such as
#: 10**12 must be an error, not an out-of-memory.
MAX_VEHICLES = 2000
VEHICLES_WHY = "a step's pairwise checks grow with the square of the count"
#: Largest inflow accepted (veh/h): above what 4 lanes carry at any speed, so larger is a typo.
MAX_INFLOW_VPH = 10_000.0


class ConfigError(DiaccError, ValueError):
    """An unknown, ill-typed or out-of-range setting, or two that contradict; one line."""


def ranged(
    default: Any, low: float, high: float | None = None, *, open_low: bool = False, why: str = ""
) -> Any:
    """A dataclass field whose value must lie in ``[low, high]`` (``(low, high]`` with
    ``open_low``; no upper bound when ``high`` is None; None itself means unset and
    passes).

    The range sits next to the field it bounds and is checked once, when the
    section is built (:func:`check_fields` in its ``__post_init__``), so that no
    code reading it checks it again. ``why`` says what the upper bound protects
    (memory, time); the error message ends with it.
    """
    return field(default=default, metadata={"range": (low, high, open_low), "why": why})


def one_of(default: str | None, choices: tuple[str, ...]) -> Any:
    """A dataclass field whose value must be one of ``choices`` (None: unset, passes)."""
    return field(default=default, metadata={"choices": choices})


class FieldError(ConfigError):
    """A field's value out of its range; :func:`diacc.config.override` prefixes the
    section's path to ``key`` so the message names the dotted key the user typed."""

    def __init__(self, key: str, problem: str) -> None:
        super().__init__(f"config key {key!r} {problem}")
        self.key, self.problem = key, problem


def check_fields(obj: Any, prefix: str = "") -> None:
    """Every float field finite, every :func:`ranged` field in range, every :func:`one_of`
    field one of its choices; a one-line :class:`FieldError` naming the first bad field.

    Nested sections check themselves; a tuple gives one value per item (``key[i]``).
    """
    for f in dataclasses.fields(obj):
        value, key = getattr(obj, f.name), f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value) or value is None:
            continue
        for item_key, item in _items(key, value):
            if isinstance(item, float) and not math.isfinite(item):
                raise FieldError(item_key, f"must be a finite number, got {item}")
        if "range" in f.metadata:
            for item_key, item in _items(key, value):
                _check_range(f, item_key, item)
        if "choices" in f.metadata and value not in f.metadata["choices"]:
            choices = f.metadata["choices"]
            names = ", ".join(c or '""' for c in choices)
            raise FieldError(key, f"must be one of {names}, got {value!r}")


def _items(key: str, value: Any) -> list[tuple[str, Any]]:
    """(key, value), or (``key[i]``, item) for each item of a tuple."""
    if isinstance(value, tuple):
        return [(f"{key}[{i}]", v) for i, v in enumerate(value)]
    return [(key, value)]


def _check_range(f: dataclasses.Field, key: str, value: Any) -> None:
    """A :func:`ranged` field's value (or one item of it) a number in its range."""
    low, high, open_low = f.metadata["range"]
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise FieldError(key, f"must be a number, got {value!r}")
    if str(f.type).startswith("int") and not isinstance(value, numbers.Integral):
        raise FieldError(key, f"must be an integer, got {value!r}")
    too_low = value <= low if open_low else value < low
    if too_low or (high is not None and value > high):
        why = f" ({f.metadata['why']})" if f.metadata.get("why") and not too_low else ""
        raise FieldError(key, f"must be {range_text(low, high, open_low)}, got {value}{why}")


def _number(x: float) -> str:
    """``10000`` for 10000.0, else as Python writes it."""
    return str(int(x)) if float(x).is_integer() else str(x)


def range_text(low: float, high: float | None, open_low: bool) -> str:
    if high is None:
        return f"{'>' if open_low else '>='} {_number(low)}"
    return f"in {'(' if open_low else '['}{_number(low)}, {_number(high)}]"
