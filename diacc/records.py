"""Batched records: dataclasses whose fields declare their env axis, with the row
operations every such record needs written once (issue 59).

Everything a step of E envs carries is a batch: the traffic state, the
observations, the reward terms, the team reward. Each field of such a record
declares how it is indexed by env, and :class:`Batched` derives from that what
used to be written per type:

* :func:`per_env` ``("E, C")``: an array whose leading axis is the env axis E;
  the string names every axis (the shape comment, made part of the field).
* :func:`env_events` ``("env, i, j")``: (K, n) event rows whose column 0 is the
  env (collisions, arrivals), any number per env.

:meth:`Batched.concat` joins batches (env indices follow on), :meth:`Batched.rows`
selects envs as a batch of their own, :meth:`Batched.env` is one env as a batch of
one, :meth:`Batched.where_rows` zeroes the envs not kept (a crashed simulator's),
and :meth:`Batched.unbatched` is one env without its env axis: the PettingZoo
edge's view, the one place the batch axis goes ((E,) fields become Python
scalars).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any, TypeVar

import numpy as np

_AXES_KEY = "diacc.record_axes"
#: The declared axes of an events field (its rows' column 0 is the env).
EVENTS = "events"


def per_env(axes: str = "E") -> Any:
    """A required field holding an array with the env axis first; ``axes`` names its
    axes, ``"E"`` first (``"E, C"``: one value per env and agent slot)."""
    if not axes.replace(" ", "").startswith("E"):
        raise ValueError(f"a per-env field's axes start with E, got {axes!r}")
    return dataclasses.field(metadata={_AXES_KEY: axes})


def env_events(columns: str) -> Any:
    """A required field holding (K, n) int event rows whose column 0 is the env;
    ``columns`` names the columns (``"env, i, j"``)."""
    return dataclasses.field(metadata={_AXES_KEY: EVENTS, "columns": columns})


_Plan = tuple[tuple[str, bool, bool], ...]
#: Record class -> its :func:`_plan` (read on every step, so built once per class).
_PLANS: dict[type, _Plan] = {}


def _plan(cls: type) -> _Plan:
    """``(name, is_events, env_axis_only)`` of each field of ``cls``, in order
    (``env_axis_only``: declared ``"E"``, one value per env)."""
    if cls in _PLANS:
        return _PLANS[cls]
    plan = []
    for f in dataclasses.fields(cls):
        axes = f.metadata.get(_AXES_KEY)
        if axes is None:
            raise TypeError(
                f"{cls.__name__}.{f.name} declares no axes: declare it with per_env() "
                "or env_events() (diacc.records)"
            )
        plan.append((f.name, axes == EVENTS, axes.replace(" ", "") == "E"))
    _PLANS[cls] = tuple(plan)
    return _PLANS[cls]


def where_rows(value: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """``value`` (E, ...) with the rows of the envs not ``kept`` (E,) set to 0 (same dtype)."""
    mask = kept.reshape((-1,) + (1,) * (value.ndim - 1))
    return np.where(mask, value, np.zeros((), value.dtype))


Record = TypeVar("Record", bound="Batched")


class Batched:
    """Row operations of a dataclass whose every field declares its axes (module docstring).

    Per-env fields are cut on their leading axis, whatever their other axes;
    event rows are kept, dropped and renumbered by their env column.
    """

    __slots__ = ()

    @classmethod
    def concat(cls: type[Record], records: Sequence[Record]) -> Record:
        """The ``records`` one after another as one batch (new arrays): env ``e`` of the
        k-th is env ``e + (envs before it)`` of the result."""
        sizes = [r.n_rows for r in records]
        offsets = np.cumsum([0] + sizes[:-1])
        parts = {}
        for name, is_events, _ in _plan(cls):
            values = [getattr(r, name) for r in records]
            if is_events:
                values = [v.copy() for v in values]
                for v, offset in zip(values, offsets, strict=True):
                    v[:, 0] += offset
            parts[name] = np.concatenate(values)
        return cls(**parts)

    @property
    def n_rows(self) -> int:
        """E, the envs of the batch (the leading axis of its first per-env field)."""
        name = next(name for name, is_events, _ in _plan(type(self)) if not is_events)
        return len(getattr(self, name))

    def rows(self: Record, index: np.ndarray) -> Record:
        """Envs ``index`` (int indices, or an (E,) bool mask) as a batch of their own
        (copies): env ``index[k]`` is env k of the result."""
        index = np.asarray(index)
        if index.dtype == bool:
            index = np.flatnonzero(index)
        renumber = None
        parts = {}
        for name, is_events, _ in _plan(type(self)):
            value = getattr(self, name)
            if is_events:
                if renumber is None:
                    renumber = np.full(self.n_rows, -1, np.int32)
                    renumber[index] = np.arange(len(index), dtype=np.int32)
                kept = value[renumber[value[:, 0]] >= 0]
                kept[:, 0] = renumber[kept[:, 0]]
                value = kept[np.argsort(kept[:, 0], kind="stable")]
            else:
                value = value[index]
            parts[name] = value
        return type(self)(**parts)

    def env(self: Record, e: int) -> Record:
        """Env ``e`` as a batch of one (copies)."""
        return self.rows(np.array([e]))

    def where_rows(self: Record, kept: np.ndarray) -> Record:
        """This batch with every field of the envs not ``kept`` (E,) bool set to 0 and their
        events dropped (same shapes otherwise; e.g. the envs whose simulator crashed)."""
        parts = {}
        for name, is_events, _ in _plan(type(self)):
            value = getattr(self, name)
            parts[name] = value[kept[value[:, 0]]] if is_events else where_rows(value, kept)
        return type(self)(**parts)

    def unbatched(self: Record, e: int, copy: bool = False) -> Record:
        """Env ``e`` without the env axis (views, or copies): the PettingZoo edge's view.

        Per-env fields lose their leading axis, an ``"E"`` field becomes a Python
        scalar, and event rows lose their env column.
        """
        parts: dict[str, Any] = {}
        for name, is_events, env_axis_only in _plan(type(self)):
            value = getattr(self, name)
            if is_events:
                value = value[value[:, 0] == e, 1:]
            elif env_axis_only:
                value = value[e].item()
            else:
                value = value[e].copy() if copy else value[e]
            parts[name] = value
        return type(self)(**parts)
