"""The multi-agent environment over a backend: what the agents see, do and get.

Traffic state -> observation / reward / PSAR -> actions -> backend commands:
:mod:`.env` (the PettingZoo ``ParallelEnv`` and its batched API), :mod:`.vector`
(many envs), :mod:`.episode` (one episode played through the env), and the parts
they compose (:mod:`.observation`, :mod:`.spaces`, :mod:`.lateral_frame`,
:mod:`.actions`, :mod:`.psar`, :mod:`.action_mask`, :mod:`.safety`,
:mod:`.reward`, :mod:`.metrics`). The public factories are :func:`diacc.parallel_env`
and :func:`diacc.env`.

It imports :mod:`diacc.sim` below it, never :mod:`diacc.learn`,
:mod:`diacc.experiments` or :mod:`diacc.cli`. (Not named ``env``: ``diacc.env`` is
the PettingZoo AEC factory.)
"""
