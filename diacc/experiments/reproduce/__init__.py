"""``diacc reproduce``: the paper's experiments end to end, resumable at every level.

* :mod:`.plan`: budgets, the resolved configuration, and what it implies
  (training runs, evaluation jobs, cells); pure and cheap, so the plan is
  printed before any work starts.
* :mod:`.stages`: training and evaluation, reusing the sweep and evaluation
  machinery (:mod:`diacc.experiments.scaleout`, :mod:`diacc.experiments.evaluate`).
* :mod:`.outputs`: Tables II/III, figures and the sim-to-sim transfer report,
  all computed from the evaluation files.
* :mod:`.manifest`: ``manifest.json``: invocations, versions, plan, and which
  stages are finished.
* :mod:`.pipeline`: the stages in order, each skipping what is done.

The command line is :mod:`diacc.cli.reproduce`; docs/guide/reproducing.md
has the budgets and the output layout.
"""
