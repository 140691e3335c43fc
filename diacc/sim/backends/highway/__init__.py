"""The ``highway`` backend: highway-env road geometry, traffic as NumPy arrays.

``backend`` (the :class:`HighwayBackend`), ``simstate`` (its vehicle
state, parameters and caches as typed (E, V) arrays), ``models`` (IDM, MOBIL
and collision tests on arrays) and ``road`` (the map as a highway-env
``RoadNetwork`` and lane tables).
"""
