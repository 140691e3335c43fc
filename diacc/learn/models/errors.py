"""The one exception the network package raises for bad input."""

from __future__ import annotations

from diacc.errors import DiaccError


class ModelError(DiaccError, ValueError):
    """Bad network input or configuration (unknown variant, missing key, wrong shape).

    The message is one line and names the offending item, so that a trainer can
    surface it without a traceback through torch internals.
    """
