"""The ``sumo`` backend: libsumo in a worker process.

``backend`` (the :class:`SumoBackend`, which talks to the worker),
``worker`` (what runs in that process), ``net`` (the SUMO network built from
a map with ``netconvert``) and ``vtypes`` (driver styles as vehicle types).
"""
