"""Learning: the actor and critic networks (:mod:`.models`) and the MAPPO trainer
(:mod:`.mappo`, with :mod:`.agent`, :mod:`.buffer`, :mod:`.valuenorm`) and the
checkpoint files it writes and the evaluator reads (:mod:`.checkpoint`).

It reads the observation layout of :mod:`diacc.envs` and trains on its vector
envs; it never imports :mod:`diacc.experiments` or :mod:`diacc.cli`.
"""
