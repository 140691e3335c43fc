"""Learning: the actor and critic networks (:mod:`.models`), recurrent MAPPO
(:mod:`.ppo`: rollout, GAE, the update; with :mod:`.agent`, :mod:`.buffer`,
:mod:`.valuenorm`), the run around it (:mod:`.trainer`, entered as
:func:`.mappo.train`; :mod:`.progress`) and the checkpoint files it writes and
the evaluator reads (:mod:`.checkpoint`).

It reads the observation layout of :mod:`diacc.envs` and trains on its vector
envs; it never imports :mod:`diacc.experiments` or :mod:`diacc.cli`.
"""
