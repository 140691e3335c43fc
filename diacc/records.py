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
* :func:`per_env_record`: a record of the same envs whose own fields declare
  their axes (a step's observations, reward terms, state), or None where a
  layer has none (no PSAR result without PSAR).
* :func:`per_env_items`: a list of one Python object per env (None for none):
  what does not fit an array, such as the last observations of the episodes
  that ended in a step.
* :func:`shared`: one value for the whole batch (a model constant), which
  every row operation keeps as it is.

:meth:`Batched.concat` joins batches (env indices follow on), :meth:`Batched.rows`
selects envs as a batch of their own, :meth:`Batched.env` is one env as a batch of
one, :meth:`Batched.set_rows` overwrites envs in place (new episodes' rows),
:meth:`Batched.where_rows` zeroes the envs not kept (a crashed simulator's),
:meth:`Batched.copy` is a deep copy, :meth:`Batched.padded` lengthens a named axis
(agent slots ``C``: envs of a training mix with fewer CAVs than the run's slots),
:meth:`Batched.stack` puts batches of the same envs (a rollout's steps) along a new
leading axis, :meth:`Batched.arrays` names the per-env arrays (what the learner turns
into tensors), and :meth:`Batched.unbatched` is one env
without its env axis: the PettingZoo edge's view, the one place the batch axis
goes ((E,) fields become Python scalars; a record declared ``keeps_batch``
stays a batch of one there, as the traffic state does for users who index its
row 0).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any, TypeVar

import numpy as np

_AXES_KEY = "diacc.record_axes"
#: The declared axes of an events field (its rows' column 0 is the env).
EVENTS = "events"


def per_env(axes: str = "E", pad: Any = 0) -> Any:
    """A required field holding an array with the env axis first; ``axes`` names its
    axes, ``"E"`` first (``"E, C"``: one value per env and agent slot). ``pad``: the
    value of an entry :meth:`Batched.padded` adds (an agent slot that never holds a
    CAV: 0, masks False; an action mask True, as for any slot without a CAV)."""
    if not axes.replace(" ", "").startswith("E"):
        raise ValueError(f"a per-env field's axes start with E, got {axes!r}")
    return dataclasses.field(metadata={_AXES_KEY: axes, "pad": pad})


def env_events(columns: str) -> Any:
    """A required field holding (K, n) int event rows whose column 0 is the env;
    ``columns`` names the columns (``"env, i, j"``)."""
    return dataclasses.field(metadata={_AXES_KEY: EVENTS, "columns": columns})


#: The declared axes of a record field (:func:`per_env_record`).
RECORD = "record"
#: The declared axes of a list field (:func:`per_env_items`).
ITEMS = "items"
#: The declared axes of a field of the whole batch (:func:`shared`).
SHARED = "shared"


def per_env_record(keeps_batch: bool = False) -> Any:
    """A required field holding a :class:`Batched` record of the same envs, or None.

    ``keeps_batch``: in the one-env view (:meth:`Batched.unbatched`) the record
    stays a batch of one (a copy) instead of losing its env axis.
    """
    return dataclasses.field(metadata={_AXES_KEY: RECORD, "keeps_batch": keeps_batch})


def per_env_items() -> Any:
    """A required field holding a list of one Python object per env (None for none)."""
    return dataclasses.field(metadata={_AXES_KEY: ITEMS})


def shared() -> Any:
    """A required field holding one value for the whole batch (not per env)."""
    return dataclasses.field(metadata={_AXES_KEY: SHARED})


def declared_axes(cls: type) -> tuple[tuple[str, str | None], ...]:
    """``(name, axes)`` of each field of ``cls``: the axes given to :func:`per_env`, or
    :data:`EVENTS`, :data:`RECORD`, :data:`ITEMS`, :data:`SHARED` (None: declared nowhere)."""
    return tuple((f.name, f.metadata.get(_AXES_KEY)) for f in dataclasses.fields(cls))


# Field kinds of a plan, each a way to cut a field by env.
_ARRAY, _SCALAR, _EVENTS, _RECORD, _BATCH_OF_ONE, _ITEMS, _SHARED = range(7)
_Plan = tuple[tuple[str, int], ...]
#: Record class -> its :func:`_plan` (read on every step, so built once per class).
_PLANS: dict[type, _Plan] = {}


def _kind(f: dataclasses.Field) -> int:
    """How field ``f`` is cut by env (one of the kinds above), from its declared axes."""
    axes = f.metadata[_AXES_KEY]
    if axes == EVENTS:
        return _EVENTS
    if axes == ITEMS:
        return _ITEMS
    if axes == SHARED:
        return _SHARED
    if axes == RECORD:
        return _BATCH_OF_ONE if f.metadata["keeps_batch"] else _RECORD
    return _SCALAR if axes.replace(" ", "") == "E" else _ARRAY


def _plan(cls: type) -> _Plan:
    """``(name, kind)`` of each field of ``cls``, in order."""
    if cls in _PLANS:
        return _PLANS[cls]
    plan = []
    for f in dataclasses.fields(cls):
        if _AXES_KEY not in f.metadata:
            raise TypeError(
                f"{cls.__name__}.{f.name} declares no axes: declare it with per_env(), "
                "env_events(), per_env_record(), per_env_items() or shared() (diacc.records)"
            )
        plan.append((f.name, _kind(f)))
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
    event rows are kept, dropped and renumbered by their env column; records
    are cut by their own declarations, and a record field that is None stays None;
    a shared field is kept (the first record's, when joining).
    """

    __slots__ = ()

    @classmethod
    def concat(cls: type[Record], records: Sequence[Record]) -> Record:
        """The ``records`` one after another as one batch (new arrays): env ``e`` of the
        k-th is env ``e + (envs before it)`` of the result."""
        sizes = [r.n_rows for r in records]
        offsets = np.cumsum([0] + sizes[:-1])
        parts: dict[str, Any] = {}
        for name, kind in _plan(cls):
            values = [getattr(r, name) for r in records]
            if kind == _EVENTS:
                values = [v.copy() for v in values]
                for v, offset in zip(values, offsets, strict=True):
                    v[:, 0] += offset
            if kind == _SHARED:
                parts[name] = values[0]
            elif kind == _ITEMS:
                parts[name] = [item for v in values for item in v]
            elif values[0] is None:
                _check_all_none(cls, name, values)
                parts[name] = None
            elif kind in (_RECORD, _BATCH_OF_ONE):
                parts[name] = type(values[0]).concat(values)
            else:
                parts[name] = np.concatenate(values)
        return cls(**parts)

    @classmethod
    def stack(cls: type[Record], records: Sequence[Record]) -> Record:
        """The ``records`` (batches of the same envs: a rollout's steps) along a new leading
        axis, S: a batch whose arrays are (S, E, ...), its rows the records (a record of
        per-env arrays only, such as the observations; new arrays)."""
        plan = _plan(cls)
        if any(kind not in (_ARRAY, _SCALAR) for _, kind in plan):
            raise TypeError(f"{cls.__name__}.stack: only a record of per-env arrays stacks")
        return cls(**{name: np.stack([getattr(r, name) for r in records]) for name, _ in plan})

    def arrays(self) -> dict[str, np.ndarray]:
        """Field name -> array of each per-env array field (what the learner converts to
        tensors, :func:`diacc.learn.models.inputs.to_tensors`)."""
        return {
            name: getattr(self, name)
            for name, kind in _plan(type(self))
            if kind in (_ARRAY, _SCALAR)
        }

    @property
    def n_rows(self) -> int:
        """E, the envs of the batch (the length of its first per-env array or list, or
        of its first record)."""
        for name, kind in _plan(type(self)):
            value = getattr(self, name)
            if kind in (_RECORD, _BATCH_OF_ONE) and value is not None:
                return value.n_rows
            if kind not in (_EVENTS, _SHARED) and value is not None:
                return len(value)
        raise ValueError(f"{type(self).__name__} holds no per-env field to count its envs by")

    def rows(self: Record, index: np.ndarray) -> Record:
        """Envs ``index`` (int indices, or an (E,) bool mask) as a batch of their own
        (copies): env ``index[k]`` is env k of the result."""
        index = np.asarray(index)
        if index.dtype == bool:
            index = np.flatnonzero(index)
        renumber = None
        parts: dict[str, Any] = {}
        for name, kind in _plan(type(self)):
            value = getattr(self, name)
            if value is None or kind == _SHARED:
                pass
            elif kind == _EVENTS:
                if renumber is None:
                    renumber = np.full(self.n_rows, -1, np.int32)
                    renumber[index] = np.arange(len(index), dtype=np.int32)
                kept = value[renumber[value[:, 0]] >= 0]
                kept[:, 0] = renumber[kept[:, 0]]
                value = kept[np.argsort(kept[:, 0], kind="stable")]
            elif kind == _ITEMS:
                value = [value[i] for i in index.tolist()]
            elif kind in (_RECORD, _BATCH_OF_ONE):
                value = value.rows(index)
            else:
                value = value[index]
            parts[name] = value
        return type(self)(**parts)

    def env(self: Record, e: int) -> Record:
        """Env ``e`` as a batch of one (copies)."""
        return self.rows(np.array([e]))

    def set_rows(self: Record, index: np.ndarray, part: Record) -> None:
        """Make envs ``index`` (int indices) of this batch those of ``part``, a batch of
        ``len(index)`` envs, in place (copies): env k of ``part`` becomes env ``index[k]``;
        their event rows replace the envs' own (e.g. new episodes' first states)."""
        index = np.asarray(index)
        for name, kind in _plan(type(self)):
            value, new = getattr(self, name), getattr(part, name)
            if value is None or kind == _SHARED:
                continue
            if kind == _EVENTS:
                own = new.copy()
                own[:, 0] = index[own[:, 0]]
                value = np.concatenate([value[~np.isin(value[:, 0], index)], own])
                setattr(self, name, value[np.argsort(value[:, 0], kind="stable")])
            elif kind == _ITEMS:
                for k, e in enumerate(index.tolist()):
                    value[e] = new[k]
            elif kind in (_RECORD, _BATCH_OF_ONE):
                value.set_rows(index, new)
            else:
                value[index] = new

    def where_rows(self: Record, kept: np.ndarray) -> Record:
        """This batch with every field of the envs not ``kept`` (E,) bool set to 0 (None in
        lists) and their events dropped (same shapes otherwise; e.g. the envs whose
        simulator crashed)."""
        parts: dict[str, Any] = {}
        for name, kind in _plan(type(self)):
            value = getattr(self, name)
            if value is None or kind == _SHARED:
                pass
            elif kind == _EVENTS:
                value = value[kept[value[:, 0]]]
            elif kind == _ITEMS:
                value = [v if k else None for v, k in zip(value, kept.tolist(), strict=True)]
            elif kind in (_RECORD, _BATCH_OF_ONE):
                value = value.where_rows(kept)
            else:
                value = where_rows(value, kept)
            parts[name] = value
        return type(self)(**parts)

    def copy(self: Record) -> Record:
        """A deep copy: no array is shared with this batch (records copied as their own
        declarations say, lists copied; other values, such as shared numbers, kept)."""
        parts: dict[str, Any] = {}
        for name, kind in _plan(type(self)):
            value = getattr(self, name)
            if isinstance(value, (np.ndarray, Batched)):
                value = value.copy()
            elif kind == _ITEMS:
                value = list(value)
            parts[name] = value
        return type(self)(**parts)

    def padded(self: Record, axis: str, size: int, batched: bool = True) -> Record:
        """This batch with every array's axis named ``axis`` (``"C"``) lengthened to
        ``size`` with its field's ``pad`` value (:func:`per_env`); new arrays where one
        grows, the others kept. ``batched=False``: a one-env view (:meth:`unbatched`),
        whose arrays lack the leading E. Records and the records of a list are padded
        by their own declarations; events, shared values and other items are kept.
        """
        parts: dict[str, Any] = {}
        for f in dataclasses.fields(type(self)):  # type: ignore[arg-type]
            value, kind = getattr(self, f.name), _kind(f)
            if value is None or kind in (_EVENTS, _SHARED):
                pass
            elif kind in (_RECORD, _BATCH_OF_ONE):
                value = value.padded(axis, size, batched or kind == _BATCH_OF_ONE)
            elif kind == _ITEMS:
                value = [
                    v.padded(axis, size, False) if isinstance(v, Batched) else v for v in value
                ]
            else:
                names = [a.strip() for a in f.metadata[_AXES_KEY].split(",")][0 if batched else 1 :]
                if axis in names:
                    value = _pad_axis(value, names.index(axis), size, f.metadata["pad"])
            parts[f.name] = value
        return type(self)(**parts)

    def unbatched(self: Record, e: int, copy: bool = False) -> Record:
        """Env ``e`` without the env axis (views, or copies): the PettingZoo edge's view.

        Per-env fields lose their leading axis, an ``"E"`` field becomes a Python
        scalar, event rows lose their env column, a list gives its item, and a
        record its own view (a ``keeps_batch`` one: env ``e`` as a batch of one).
        """
        parts: dict[str, Any] = {}
        for name, kind in _plan(type(self)):
            value = getattr(self, name)
            if value is None or kind == _SHARED:
                pass
            elif kind == _EVENTS:
                value = value[value[:, 0] == e, 1:]
            elif kind == _SCALAR:
                value = value[e].item()
            elif kind == _ITEMS:
                value = value[e]
            elif kind == _RECORD:
                value = value.unbatched(e, copy)
            elif kind == _BATCH_OF_ONE:
                value = value.env(e)
            else:
                value = value[e].copy() if copy else value[e]
            parts[name] = value
        return type(self)(**parts)


def _pad_axis(value: np.ndarray, axis: int, size: int, fill: Any) -> np.ndarray:
    """``value`` with axis ``axis`` lengthened to ``size`` by entries ``fill`` (itself
    when it is as long already)."""
    missing = size - value.shape[axis]
    if missing < 0:
        raise ValueError(f"cannot pad axis {axis} of length {value.shape[axis]} to {size}")
    if missing == 0:
        return value
    shape = list(value.shape)
    shape[axis] = missing
    return np.concatenate([value, np.full(shape, fill, value.dtype)], axis=axis)


def _check_all_none(cls: type, name: str, values: list) -> None:
    """``ValueError`` unless field ``name`` is None in every record joined."""
    if any(v is not None for v in values):
        raise ValueError(f"{cls.__name__}.concat: {name} is None in some records, not all")
    return None
