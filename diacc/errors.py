"""The base of every error that means "the user asked for something we cannot do".

The ``diacc`` command prints a :class:`DiaccError` as one ``diacc: error:``
line and exits with code 2; any other exception is a bug and keeps its
traceback. Each module raises its own subclass (``ConfigError``,
``MapError``, ...), which also keeps its builtin base (``ValueError`` or
``RuntimeError``) so that library callers can catch either.
"""

from __future__ import annotations


class DiaccError(Exception):
    """A user mistake or a failure outside diacc (dead simulator, missing Ray); one line."""


class MapError(DiaccError, ValueError):
    """A map file or map name is invalid; the message is one line. Here rather than in
    :mod:`diacc.sim.maps` because :mod:`diacc.sim.mapgen`, which maps builds on, raises it."""
