"""Axes declared by each field of the highway backend's batch records, and the
vehicle-window operations of those records.

The records (:mod:`.simstate`'s three, and :class:`~.models.IdmParams` nested in
one of them) are :class:`~diacc.records.Batched` records like every batch above
the simulator, so they get the env-axis operations from there (``env(e)``, ``rows``,
``set_rows``, ``concat``). Every field says what its value is indexed by:
:func:`per_env` (E,), :func:`per_vehicle` (E, V), :func:`per_pair` (E, V, V),
:func:`shared` (one value for the whole batch, not an array) or :func:`nested` (a
record whose fields say their own), declarations of :mod:`diacc.records`. The
backend steps only a window ``lo:hi`` of the vehicles (:meth:`EnvRows.window`,
:meth:`EnvRows.put_window`), and a field is cut by what it declares, not by its
number of dimensions, which cannot tell: an (E, 3) per-env field would be cut as
if per vehicle, an (E, V, 2) one as if pairwise. A field that declares nothing,
or whose value does not have exactly its declared axes, is an error naming it,
not a guess.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
from typing import Any, TypeVar

import numpy as np

from diacc import records
from diacc.records import Batched


class Axes(enum.Enum):
    """What a record field is indexed by (E: env of the batch, V: vehicle)."""

    ENV = "(E,)"
    VEHICLE = "(E, V)"
    PAIR = "(E, V, V)"
    SHARED = "one value for the batch"
    NESTED = "a record of declared fields"


#: Number of dimensions of the array kinds.
_NDIM = {Axes.ENV: 1, Axes.VEHICLE: 2, Axes.PAIR: 3}
#: What each of :mod:`diacc.records`' declarations used here means (axes without spaces).
_KINDS = {
    "E": Axes.ENV,
    "E,V": Axes.VEHICLE,
    "E,V,V": Axes.PAIR,
    records.SHARED: Axes.SHARED,
    records.RECORD: Axes.NESTED,
}


def per_env() -> Any:
    """A required field holding an (E,) array: one value per env."""
    return records.per_env("E")


def per_vehicle() -> Any:
    """A required field holding an (E, V) array: one value per vehicle of each env."""
    return records.per_env("E, V")


def per_pair() -> Any:
    """A required field holding an (E, V, V) array: one value per vehicle pair of each env."""
    return records.per_env("E, V, V")


shared = records.shared
nested = records.per_env_record


@functools.cache
def field_axes(cls: type) -> tuple[tuple[str, Axes], ...]:
    """``(name, axes)`` of every field of the record class ``cls``, in order.

    Raises ``TypeError`` naming the first field that declares no axes.
    """
    out = []
    for name, axes in records.declared_axes(cls):
        kind = None if axes is None else _KINDS.get(axes.replace(" ", ""))
        if kind is None:
            raise TypeError(
                f"{cls.__name__}.{name} declares no axes: declare it with per_env(), "
                "per_vehicle(), per_pair(), shared() or nested() (diacc.sim.backends.highway.rows)"
            )
        out.append((name, kind))
    return tuple(out)


@functools.cache
def _plan(cls: type) -> tuple[tuple[str, Axes, int], ...]:
    """:func:`field_axes` with each kind's number of array axes (0: not an array), which
    the window loops below branch on: they run on every step, so they look up little."""
    return tuple((name, kind, _NDIM.get(kind, 0)) for name, kind in field_axes(cls))


def _check(record: Any, name: str, kind: Axes, value: Any) -> None:
    """``ValueError`` naming the field unless ``value`` has the declared axes ``kind``."""
    is_array = isinstance(value, np.ndarray)
    if kind in _NDIM:
        fits = is_array and value.ndim == _NDIM[kind]
    else:
        is_record = dataclasses.is_dataclass(value) and not isinstance(value, type)
        fits = is_record if kind is Axes.NESTED else not (is_array or is_record)
    if not fits:
        held = f"an array of shape {value.shape}" if is_array else f"a {type(value).__name__}"
        raise ValueError(
            f"{type(record).__name__}.{name} is declared {kind.value} but holds {held}"
        )


def _window(record: Any, lo: int, hi: int) -> Any:
    """Vehicles ``lo:hi`` of ``record``, cut by each field's declared axes (``ndim`` is the
    declared kind's, from :func:`_plan`; the array's own only has to agree with it)."""
    parts = {}
    for name, kind, ndim in _plan(type(record)):
        value = getattr(record, name)
        if ndim and isinstance(value, np.ndarray) and value.ndim == ndim:  # the common case
            if ndim == 2:
                value = value[:, lo:hi]
            elif ndim == 3:
                value = value[:, lo:hi, lo:hi]
        else:
            _check(record, name, kind, value)
            if kind is Axes.NESTED:
                value = _window(value, lo, hi)
        parts[name] = value
    return type(record)(**parts)


def _put_window(target: Any, part: Any, lo: int, hi: int) -> None:
    """Vehicle fields are written into ``target``'s arrays; per-env and shared fields
    are taken over whole (a field ``part`` shares with ``target`` is not set again,
    so a frozen record such as :class:`~.models.IdmParams` is written in place)."""
    for name, kind, ndim in _plan(type(target)):
        old, new = getattr(target, name), getattr(part, name)
        if not (ndim and isinstance(old, np.ndarray) and old.ndim == ndim):
            _check(target, name, kind, old)
        if new is not old and not (ndim and isinstance(new, np.ndarray) and new.ndim == ndim):
            _check(part, name, kind, new)
        if ndim == 2:
            old[:, lo:hi] = new
        elif ndim == 3:
            old[:, lo:hi, lo:hi] = new
        elif kind is Axes.NESTED:
            _put_window(old, new, lo, hi)
        elif new is not old:
            setattr(target, name, new)


_Rows = TypeVar("_Rows", bound="EnvRows")


class EnvRows(Batched):
    """The vehicle-window operations of the batch records; the env-axis ones (and the deep
    copy) are :class:`~diacc.records.Batched`'s."""

    __slots__ = ()

    def window(self: _Rows, lo: int, hi: int) -> _Rows:
        """Vehicles ``lo:hi`` of every env as a record of views, cut by each field's axes
        (per-env and shared fields are shared as they are).

        The highway backend steps only this window of vehicles (the others are
        settled: arrived, or not due to enter); :meth:`put_window` writes a
        stepped window back.
        """
        return _window(self, lo, hi)

    def put_window(self: _Rows, lo: int, hi: int, part: _Rows) -> None:
        """Write ``part``, a stepped :meth:`window` ``lo:hi`` of ``self``, back into ``self``."""
        _put_window(self, part, lo, hi)
