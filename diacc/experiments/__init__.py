"""Experiments: what runs the layers below for a question and reports the answer.

Policies (baselines, scripted CAVs, checkpoints) and evaluation grids
(:mod:`.policies`, :mod:`.grid`, :mod:`.evaluate`), a trained agent for Python
users (:mod:`.agent`, :func:`diacc.load_policy`), tables, figures, renders
(:mod:`.report`, :mod:`.plots`, :mod:`.render`, :mod:`.timespace`), sweeps and
their scale-out (:mod:`.sweepaxes`, :mod:`.scaleout`, :mod:`.workpool`), the
benchmarks of ``diacc bench`` (:mod:`.bench`) and ``diacc reproduce``
(:mod:`.reproduce`). It never imports :mod:`diacc.cli`.
"""
