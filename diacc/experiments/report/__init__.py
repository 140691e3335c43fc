"""Paper-style result tables (Tables II-III) from evaluation results directories.

One column per evaluated policy (one results directory each), and for every
grid cell the paper's three rows, plus two optional ones (``rows``):

* **Speed (m/s)**: mean +- std over all vehicles and steps of all episodes,
  as in the paper (pooled exactly from each episode's mean, std and sample
  count); ``speed_std="episodes"`` gives mean +- std of the episode means
  instead.
* **p(WE) (%)**, **p(SCE) (%)**: mean +- std over episodes of the per-episode
  shares (population std, ddof = 0).
* optional **Collision (%)**: share of episodes that ended in a collision;
  **Arrived (%)**: mean share of vehicles that reached the route end;
  the flow rows (:data:`FLOW_ROWS`, definitions in :mod:`diacc.envs.metrics`),
  each mean +- std over episodes: **Throughput (veh/h)**, **Delay (s/veh)**,
  **Arrived speed (m/s)**, **Travel time (s)** (of arrived vehicles),
  **Never arrived (%)**.

Each entry also shows its change against the ``pure-hdv`` column and
against the ``same-mix`` column of the same backend (when given;
:data:`REFERENCES`); the change against same-mix is paired episode by episode
(the same seed is the same traffic) and carries its 95 % bootstrap interval
(:mod:`diacc.experiments.paired`), marked :data:`NO_DIFFERENCE` where the
interval holds 0: relative, ``(mean - mean_ref) / mean_ref`` in %, for
speeds, flows and times, and a difference in percentage points (pp) for
shares, since "-100 %" for a share going from 14 % to 0 % reads worse than
"-14.0 pp". Pure HDV redraws every driver, same-mix keeps the CAV policy's
vehicles and hands its CAV slots to human drivers, so only the second change
is what the CAVs' control does.

Emphasis follows the paper's Tables II/III: per row, the best value is bold
and the second best underlined (italic in Markdown), compared at the printed
precision (higher speed / arrived share, lower shares). Columns are ranked
only against columns of the same backend: the two simulators' traffic is not
the same, so a highway column is never "better" than a sumo one. Unlike the
paper, a column is ranked in a cell only when the ranking means something
there (:data:`RANKING_RULE`): it is no slower than the pure-HDV column of the
same backend and its collision rate is no higher. A policy that is slower or
crashes more than human traffic is never bold for one metric out of context.
Output as Markdown, LaTeX (booktabs, multirow: :data:`LATEX_PREAMBLE`) or a
tidy CSV.

Modules: :mod:`.table` (the table, its metrics and comparison rules), :mod:`.collect`
(a table from results directories), :mod:`.formats` (Markdown, LaTeX, CSV); their
public names are importable from here.
"""

from diacc.experiments.report.collect import (
    SPEED_STD,
    TRAINING_RUN,
    build_table,
    expand_rows,
    table_from_results,
)
from diacc.experiments.report.formats import (
    FORMATS,
    LATEX_PREAMBLE,
    render_table,
    to_csv,
    to_latex,
    to_markdown,
)
from diacc.experiments.report.table import (
    CHANGE_RULE,
    DEFAULT_ROWS,
    FLOW_ROWS,
    METRICS,
    NO_DIFFERENCE,
    PAIRED_REFERENCE,
    RANKING_RULE,
    REFERENCE,
    REFERENCES,
    Stat,
    Table,
    change_unit,
    interval_rule,
)

__all__ = [
    "TRAINING_RUN",
    "CHANGE_RULE",
    "DEFAULT_ROWS",
    "FLOW_ROWS",
    "FORMATS",
    "LATEX_PREAMBLE",
    "METRICS",
    "NO_DIFFERENCE",
    "PAIRED_REFERENCE",
    "RANKING_RULE",
    "REFERENCE",
    "REFERENCES",
    "SPEED_STD",
    "Stat",
    "Table",
    "build_table",
    "change_unit",
    "expand_rows",
    "interval_rule",
    "render_table",
    "table_from_results",
    "to_csv",
    "to_latex",
    "to_markdown",
]
