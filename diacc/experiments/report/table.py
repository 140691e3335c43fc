"""The table of :mod:`diacc.experiments.report`: its metrics, entries and the rules that
compare columns (changes against the references, paired intervals, best / second best).

Columns are compared only with columns of the same backend: the two simulators' traffic
is not the same, so a highway column is never "better" than a sumo one.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from diacc.experiments.grid import Cell
from diacc.experiments.paired import EpisodeValues, PairedChange, paired_change

#: (key, row label, higher is better, episodes.csv column, display scale); shares
#: are shown in percent (scale 100). Results written before a column existed lack
#: its row (older ``episodes.csv`` files have no flow columns).
METRICS = (
    ("speed", "Speed (m/s)", True, "mean_speed_mps", 1.0),
    ("p_we", "p(WE) (%)", False, "p_we", 100.0),
    ("p_sce", "p(SCE) (%)", False, "p_sce", 100.0),
    ("collision", "Collision (%)", False, "collision", 100.0),
    ("arrived", "Arrived (%)", True, "arrived_fraction", 100.0),
    ("throughput", "Throughput (veh/h)", True, "throughput_vph", 1.0),
    ("delay", "Delay (s/veh)", False, "delay_per_vehicle_s", 1.0),
    ("arrived_speed", "Arrived speed (m/s)", True, "mean_arrived_speed_mps", 1.0),
    ("travel_time", "Travel time (s)", False, "mean_travel_time_s", 1.0),
    ("never_arrived", "Never arrived (%)", False, "never_arrived_fraction", 100.0),
)
#: Rows of the paper's tables; the others are optional.
DEFAULT_ROWS = ("speed", "p_we", "p_sce")
#: The flow rows (``--rows`` shorthand ``flow``).
FLOW_ROWS = ("throughput", "delay", "arrived_speed", "travel_time", "never_arrived")
REFERENCE = "pure-hdv"
#: Columns every other column is compared with, in the order shown.
REFERENCES = (REFERENCE, "same-mix")
RANKING_RULE = (
    "bold: best, underlined (Markdown: italic): second best of a row among the columns of "
    "one backend, as in the paper; ranked only columns no slower and with no more "
    "collisions than pure HDV on that backend"
)
CHANGE_RULE = "changes in % for speeds, flows and times, in percentage points (pp) for shares"
#: Marks a paired change whose 95 % interval holds 0.
NO_DIFFERENCE = "≈"
#: The policy whose column the paired changes and intervals are taken against by default.
PAIRED_REFERENCE = "same-mix"


def interval_rule(reference: str) -> str:
    """The table note that explains the intervals against ``reference``."""
    return (
        f"[low, high]: 95 % bootstrap interval of the change against {reference}, over the "
        "episodes both played with the same seed (the same traffic; a column pooling "
        "training seeds resamples them too); "
        f"{NO_DIFFERENCE}: the interval holds 0, no measurable difference"
    )


#: Display scale of each metric (100: a share shown in percent).
_SCALE = {key: scale for key, _, _, _, scale in METRICS}


@dataclass(frozen=True)
class Stat:
    """A table entry in display units."""

    mean: float
    std: float
    n_episodes: int


@dataclass
class Table:
    columns: list[str]  # column labels, in the order given
    cells: list[Cell]
    stats: dict[tuple[str, str, str], Stat]  # (cell key, metric, column) -> entry
    notes: list[str]
    policy: dict[str, str]  # column -> policy name
    backend: dict[str, str]  # column -> backend name
    rows: tuple[str, ...] = DEFAULT_ROWS  # metrics shown, in order
    caption: str = ""
    # (cell key, metric, column) -> per-episode values, for the paired changes
    values: dict[tuple[str, str, str], EpisodeValues] = dataclasses.field(default_factory=dict)
    # the paired changes' reference: a policy name, or a column label (a results directory's)
    paired_against: str = PAIRED_REFERENCE

    def paired(self, cell: Cell, metric: str, column: str) -> PairedChange | None:
        """Change against the :attr:`paired_against` column (same-mix) of the same backend
        over the episodes both played on the same seed, with its 95 % interval (None where
        there is no such column, this is it or pure HDV, or fewer than 2 episodes pair)."""
        ref = self._paired_reference(column)
        if ref is None:
            return None
        mine = self.values.get((cell.key, metric, column))
        theirs = self.values.get((cell.key, metric, ref))
        if mine is None or theirs is None:
            return None
        return paired_change(mine, theirs, relative=change_unit(metric) == "%")

    def _paired_reference(self, column: str) -> str | None:
        """The column :meth:`paired` compares ``column`` with: :attr:`paired_against` as a
        column label (a results directory's), else that policy's column of the same
        backend; None for pure HDV and for the reference itself."""
        if self.policy[column] == REFERENCE or column == self.paired_against:
            return None
        if self.paired_against in self.columns:
            ref = self.paired_against
            return ref if self.backend[ref] == self.backend[column] else None
        if self.policy[column] == self.paired_against:
            return None
        return self.reference(column, self.paired_against)

    def reference(self, column: str, policy: str = REFERENCE) -> str | None:
        """The column of ``policy`` (pure HDV, same-mix) of the same backend a column is
        compared with, if any (columns of different backends are never compared)."""
        same = [
            c
            for c in self.columns
            if self.policy[c] == policy and self.backend[c] == self.backend[column]
        ]
        return same[0] if same else None

    def change(self, cell: Cell, metric: str, column: str, policy: str = REFERENCE) -> float | None:
        """Change of the mean against the ``policy`` column (None if undefined; pure HDV is
        compared with nothing, same-mix with pure HDV): percent, or percentage points for
        shares (:func:`change_unit`)."""
        ref = self.reference(column, policy)
        if ref is None or self.policy[column] in (REFERENCE, policy):
            return None
        a, b = self.stats.get((cell.key, metric, column)), self.stats.get((cell.key, metric, ref))
        if a is None or b is None or not math.isfinite(b.mean):
            return None
        if change_unit(metric) == "pp":
            return a.mean - b.mean  # shares are stored in percent already
        return None if b.mean == 0 else 100.0 * (a.mean - b.mean) / b.mean

    def _rounded(self, cell: Cell, metric: str, column: str) -> float | None:
        stat = self.stats.get((cell.key, metric, column))
        return round(stat.mean, 2) if stat is not None and math.isfinite(stat.mean) else None

    def ranked(self, cell: Cell, column: str) -> bool:
        """Whether a column takes part in a cell's best / second-best marks (RANKING_RULE).

        Compared at the printed precision with the pure-HDV reference: not
        slower, and no more collisions (where both logged them).
        """
        ref = self.reference(column)
        if ref is None or ref == column:
            return True
        for metric, sign in (("speed", 1.0), ("collision", -1.0)):
            mine, theirs = self._rounded(cell, metric, column), self._rounded(cell, metric, ref)
            if mine is not None and theirs is not None and sign * (mine - theirs) < 0:
                return False
        return True

    def marks(self, cell: Cell, metric: str) -> tuple[set[str], set[str]]:
        """(best, second-best) columns of a row, ranked within each backend; second best
        only where a backend has 3+ ranked columns."""
        higher = next(m[2] for m in METRICS if m[0] == metric)
        best: set[str] = set()
        second: set[str] = set()
        for backend in dict.fromkeys(self.backend[c] for c in self.columns):
            values = {
                c: v
                for c in self.columns
                if self.backend[c] == backend
                and self.ranked(cell, c)
                and (v := self._rounded(cell, metric, c)) is not None
            }
            if len(values) < 2:
                continue
            order = sorted(set(values.values()), reverse=higher)
            best |= {c for c, v in values.items() if v == order[0]}
            if len(values) >= 3 and len(order) > 1:
                second |= {c for c, v in values.items() if v == order[1]}
        return best, second

    def best(self, cell: Cell, metric: str) -> set[str]:
        """Columns holding the best value of a row (see :meth:`marks`)."""
        return self.marks(cell, metric)[0]


def change_unit(metric: str) -> str:
    """``"pp"`` (percentage points) for shares, ``"%"`` (a relative change) for the rest."""
    return "pp" if _SCALE[metric] == 100.0 else "%"
