"""Simulator backends: the protocol (:mod:`diacc.sim.backends.base`) and its
implementations, one package each (``highway``, ``sumo``).

The implementations are registered here, by name, with a function that imports
them on first use: the protocol module stays below its implementations (they
import it, never the other way round), and ``import diacc`` loads neither
highway-env nor libsumo.
"""

from __future__ import annotations

from diacc.sim.backends.base import Backend, register_backend


def _highway() -> type[Backend]:
    from diacc.sim.backends.highway.backend import HighwayBackend

    return HighwayBackend


def _sumo() -> type[Backend]:
    from diacc.sim.backends.sumo.backend import SumoBackend

    return SumoBackend


register_backend("highway", _highway)
register_backend("sumo", _sumo)
