"""Learning: the actor and critic networks (:mod:`.models`), recurrent MAPPO
(:mod:`.ppo`: rollout, GAE, the update; with :mod:`.agent`, :mod:`.buffer`,
:mod:`.valuenorm`), the run around it (:mod:`.trainer`, entered as
:func:`.mappo.train`; :mod:`.progress`), the checkpoint files it writes and
the evaluator reads (:mod:`.checkpoint`) and the one way a trained actor acts,
in training and evaluation alike (:mod:`.acting`).

It reads the observation layout of :mod:`diacc.envs` and trains on its vector
envs; it never imports :mod:`diacc.experiments` or :mod:`diacc.cli`.
"""
