"""The ``highway`` backend: highway-env road geometry, traffic as NumPy arrays.

``backend`` (the :class:`HighwayBackend`, which coordinates the rest: resets,
the decision step, the active window), ``insertion`` (the records of a reset,
departures), ``lanes`` (CAV commands, MOBIL, forced merges, yielding),
``dynamics`` (one integration sub-step and the caches it reads), ``export``
(the shared TrafficState), ``simstate`` (vehicle state, parameters and caches
as typed (E, V) arrays), ``rows`` (the axes each record field declares, and the
row and vehicle-window operations they allow), ``models`` (IDM, MOBIL and
collision tests on arrays) and ``road`` (the map as a highway-env ``RoadNetwork`` and lane tables).
"""
