"""The road and its traffic: maps, scenarios, the simulator backends and the
:class:`~diacc.sim.state.TrafficState` they return.

Lowest layer of the data flow (map + scenario -> backend -> traffic state): it
imports none of :mod:`diacc.envs`, :mod:`diacc.learn`, :mod:`diacc.experiments`
or :mod:`diacc.cli`.
"""
