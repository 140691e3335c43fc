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
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from diacc.experiments.evaluate import EvaluationError, csv_text, load_episodes
from diacc.experiments.grid import CELL_KEYS, Cell
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
FORMATS = ("markdown", "latex", "csv")
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
        "episodes both played with the same seed (the same traffic); "
        f"{NO_DIFFERENCE}: the interval holds 0, no measurable difference"
    )


#: Display scale of each metric (100: a share shown in percent).
_SCALE = {key: scale for key, _, _, _, scale in METRICS}
#: What a LaTeX document needs for :func:`to_latex`'s output.
LATEX_PREAMBLE = "\\usepackage{booktabs}\n\\usepackage{multirow}"
SPEED_STD = ("samples", "episodes")


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
    paired_against: str = PAIRED_REFERENCE  # policy of the paired changes' reference column

    def paired(self, cell: Cell, metric: str, column: str) -> PairedChange | None:
        """Change against the :attr:`paired_against` column (same-mix) of the same backend
        over the episodes both played on the same seed, with its 95 % interval (None where
        there is no such column, this is it or pure HDV, or fewer than 2 episodes pair)."""
        ref = self.reference(column, self.paired_against)
        if ref is None or self.policy[column] in (REFERENCE, self.paired_against):
            return None
        mine = self.values.get((cell.key, metric, column))
        theirs = self.values.get((cell.key, metric, ref))
        if mine is None or theirs is None:
            return None
        return paired_change(mine, theirs, relative=change_unit(metric) == "%")

    def reference(self, column: str, policy: str = REFERENCE) -> str | None:
        """The column of ``policy`` (pure HDV, same-mix) of the same backend a column is
        compared with, if any (columns of different backends are never compared)."""
        same = [
            c
            for c in self.columns
            if self.policy[c] == policy and self.backend[c] == self.backend[column]
        ]
        return (same or [None])[0]

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


def _float(text: str | None) -> float:
    return float(text) if text not in (None, "", "nan") else float("nan")


def _speed_stat(rows: list[dict[str, str]], speed_std: str) -> Stat:
    means = np.array([_float(r["mean_speed_mps"]) for r in rows])  # (K,)
    if speed_std == "episodes":
        return Stat(float(means.mean()), float(means.std()), len(rows))
    stds = np.array([_float(r["std_speed_mps"]) for r in rows])  # (K,)
    counts = np.array([int(r["n_speed_samples"]) for r in rows], dtype=float)  # (K,)
    total = counts.sum()
    mean = float((counts * means).sum() / total)
    second_moment = float((counts * (stds**2 + means**2)).sum() / total)
    return Stat(mean, math.sqrt(max(second_moment - mean**2, 0.0)), len(rows))


def _episode_stat(rows: list[dict[str, str]], key: str, scale: float) -> Stat | None:
    """Mean +- std over episodes (times ``scale``, 100 for percent) of the episodes where
    the value is defined; None if the results lack the column or every value is nan."""
    if key not in rows[0]:
        return None
    values = scale * np.array([_float(r[key]) for r in rows])  # (K,)
    values = values[np.isfinite(values)]
    if not values.size:
        return None
    return Stat(float(values.mean()), float(values.std()), int(values.size))


def _episode_values(
    rows: list[dict[str, str]], metric: str, column: str, scale: float, speed_std: str
) -> EpisodeValues | None:
    """Per-episode values of a metric keyed by seed (None without seeds or the column);
    speed weighted by its sample count where the table pools samples."""
    if "seed" not in rows[0] or column not in rows[0]:
        return None
    weight = np.ones(len(rows))  # (K,)
    if metric == "speed" and speed_std == "samples":
        weight = np.array([float(r["n_speed_samples"]) for r in rows])
    return EpisodeValues(
        seed=np.array([int(r["seed"]) for r in rows], dtype=np.int64),
        value=scale * np.array([_float(r[column]) for r in rows]),
        weight=weight,
    )


def _episodes(counts: list[int]) -> str:
    """``1 episode``, ``5 episodes``, ``3/5 episodes`` (cells with different counts)."""
    return f"{'/'.join(map(str, counts))} episode{'' if counts == [1] else 's'}"


def _budget(meta: dict) -> str:
    """How long a checkpoint was trained, for the caption ("" for baselines)."""
    if "checkpoint" not in meta:
        return ""
    steps = meta.get("trained_steps")
    text = f"checkpoint update {meta.get('update', '?')}"
    if steps is not None:
        text += f", {steps:,} of {meta.get('total_steps', steps):,} training steps"
    return text + f" on {meta.get('trained_on', '?')}"


def build_table(
    result_dirs: list[str | Path],
    speed_std: str = "samples",
    rows: tuple[str, ...] | list[str] = DEFAULT_ROWS,
    paired_against: str = PAIRED_REFERENCE,
) -> Table:
    """Collect the statistics of several results directories into one table; changes
    against the ``paired_against`` policy's column carry their interval."""
    _check_options(speed_std, rows)
    if not result_dirs:
        raise EvaluationError("give at least one results directory")
    loaded = [(Path(d), *load_episodes(d)) for d in result_dirs]
    policies = {meta["policy"] for _, meta, _ in loaded}
    if paired_against not in policies and paired_against != PAIRED_REFERENCE:
        raise EvaluationError(
            f"--paired-against {paired_against}: no results directory holds that policy "
            f"(these hold {', '.join(sorted(policies))})"
        )
    table = table_from_results(loaded, speed_std, rows)
    if paired_against != PAIRED_REFERENCE:
        notes = [
            interval_rule(paired_against) if n == interval_rule(PAIRED_REFERENCE) else n
            for n in table.notes
        ]
        if interval_rule(paired_against) not in notes:
            notes.insert(-2, interval_rule(paired_against))
        table = dataclasses.replace(table, paired_against=paired_against, notes=notes)
    return table


def expand_rows(text: str) -> tuple[str, ...]:
    """Row names of a comma-separated ``--rows`` value; ``flow`` stands for :data:`FLOW_ROWS`."""
    names = [r.strip() for r in text.split(",") if r.strip()]
    return tuple(n for name in names for n in (FLOW_ROWS if name == "flow" else (name,)))


def _check_options(speed_std: str, rows: tuple[str, ...] | list[str]) -> None:
    if speed_std not in SPEED_STD:
        raise EvaluationError(f"unknown speed std {speed_std!r}; use one of {', '.join(SPEED_STD)}")
    known = [m[0] for m in METRICS]
    unknown = [r for r in rows if r not in known]
    if unknown or not rows:
        raise EvaluationError(
            f"unknown table row {(unknown or [''])[0]!r}; use some of {', '.join(known)}"
        )


def table_from_results(
    loaded: list[tuple[Path, dict, list[dict[str, str]]]],
    speed_std: str = "samples",
    rows: tuple[str, ...] | list[str] = DEFAULT_ROWS,
) -> Table:
    """One table from (directory, meta, episode rows) per column, as :func:`load_episodes`
    reads them; rows may also be pooled from several directories (``diacc reproduce``
    pools the seeds of a variant into one column)."""
    _check_options(speed_std, rows)
    labels = [meta["policy"] for _, meta, _ in loaded]
    if len(set(labels)) < len(labels):  # same policy twice: tell them apart by backend, then dir
        labels = [f"{meta['policy']} ({meta['backend']})" for _, meta, _ in loaded]
    if len(set(labels)) < len(labels):
        labels = [f"{lab} [{d.name}]" for lab, (d, _, _) in zip(labels, loaded, strict=True)]
    stats: dict[tuple[str, str, str], Stat] = {}
    values: dict[tuple[str, str, str], EpisodeValues] = {}
    cells: dict[str, Cell] = {}
    notes: list[str] = []
    episode_counts: set[int] = set()
    for label, (_, meta, episode_rows) in zip(labels, loaded, strict=True):
        by_cell: dict[Cell, list[dict[str, str]]] = {}
        for row in episode_rows:
            cell = Cell(
                row["map"],
                int(row["n_vehicles"]),
                float(row["cav_penetration"]),
                row["style_mix"],
                float(row.get("inflow_vph") or 0.0),  # demand cells (older files: none)
                float(row.get("demand_s") or 0.0),
                float(row.get("warmup_s") or 0.0),
            )
            by_cell.setdefault(cell, []).append(row)
        for cell, cell_rows in by_cell.items():
            cells[cell.key] = cell
            stats[(cell.key, "speed", label)] = _speed_stat(cell_rows, speed_std)
            for metric, _, _, column, scale in METRICS[1:]:
                if (stat := _episode_stat(cell_rows, column, scale)) is not None:
                    stats[(cell.key, metric, label)] = stat
            for metric, _, _, column, scale in METRICS:
                found = _episode_values(cell_rows, metric, column, scale, speed_std)
                if found is not None:
                    values[(cell.key, metric, label)] = found
        first = episode_rows[0]
        version = f", {first['sumo_version']}" if first.get("sumo_version") else ""
        per_cell = sorted({len(r) for r in by_cell.values()})
        episode_counts.update(per_cell)
        budget = _budget(meta)
        notes.append(
            f"{label}: {meta['backend']} backend{version}, style preset "
            f"{first.get('style_preset', '?')}, "
            f"{_episodes(per_cell)} per cell" + (f", {budget}" if budget else "")
        )
    missing = [r for r in rows if not any(k[1] == r for k in stats)]
    if missing:
        raise EvaluationError(
            f"no results directory has the data of row {missing[0]!r} "
            "(re-run `diacc eval` into a fresh directory)"
        )
    speed_note = (
        "speed: mean ± std over all vehicles and steps"
        if speed_std == "samples"
        else "speed: mean ± std of episode means"
    )
    notes.append(f"{speed_note}; other rows: mean ± std over episodes")
    refs = [r for r in REFERENCES if r in {m["policy"] for _, m, _ in loaded}]
    if refs:
        notes.append(
            "in brackets: change of the mean against "
            + " and ".join({REFERENCE: "pure HDV", "same-mix": "same-mix"}[r] for r in refs)
            + " (same backend), in that order"
        )
    if PAIRED_REFERENCE in refs:
        notes.append(interval_rule(PAIRED_REFERENCE))
    notes.append(RANKING_RULE)
    notes.append(CHANGE_RULE)
    ordered = sorted(
        cells.values(), key=lambda c: (c.map, -c.cav_penetration, c.n_vehicles, c.style_mix)
    )
    counts = sorted(episode_counts)
    presets = dict.fromkeys(rows_[0].get("style_preset", "?") for _, _, rows_ in loaded)
    # results written before seed streams ran on the legacy one
    streams = dict.fromkeys(rows_[0].get("stream", "legacy") for _, _, rows_ in loaded)
    budgets = [
        f"{lab} {m['trained_steps']:,}"
        + (
            f" of {m['total_steps']:,}"
            if m.get("total_steps", m["trained_steps"]) != m["trained_steps"]
            else ""
        )
        for lab, (_, m, _) in zip(labels, loaded, strict=True)
        if "trained_steps" in m
    ]
    caption = (
        f"{', '.join(dict.fromkeys(c.map for c in ordered))}: {_episodes(counts)} per cell, "
        f"HDV style preset {'/'.join(presets)}, seed stream {'/'.join(streams)}"
        + (f"; training budget (env steps): {', '.join(budgets)}" if budgets else "")
    )
    return Table(
        labels,
        ordered,
        stats,
        notes,
        policy={lab: m["policy"] for lab, (_, m, _) in zip(labels, loaded, strict=True)},
        backend={lab: m["backend"] for lab, (_, m, _) in zip(labels, loaded, strict=True)},
        rows=tuple(rows),
        caption=caption,
        values=values,
    )


def change_unit(metric: str) -> str:
    """``"pp"`` (percentage points) for shares, ``"%"`` (a relative change) for the rest."""
    return "pp" if _SCALE[metric] == 100.0 else "%"


# ----------------------------------------------------------------------------- rendering
def _size(cell: Cell) -> str:
    """``N=25`` for a release cell, ``Q=3200 veh/h`` for a demand cell (N follows from Q)."""
    return f"Q={cell.inflow_vph:.0f} veh/h" if cell.inflow_vph else f"N={cell.n_vehicles}"


def _scenario(cell: Cell) -> str:
    return f"{_size(cell)}, rho={cell.cav_penetration:.1f}, {cell.style_mix}"


def _label(metric: str) -> str:
    return next(m[1] for m in METRICS if m[0] == metric)


def _entry(
    table: Table,
    cell: Cell,
    metric: str,
    column: str,
    marks: tuple[str, str, str, str],
    percent: str = "%",
) -> str:
    """One entry; ``marks`` = (best open, best close, second open, second close)."""
    stat = table.stats.get((cell.key, metric, column))
    if stat is None:
        return "—"
    text = f"{stat.mean:.2f} ± {stat.std:.2f}"
    best, second = table.marks(cell, metric)
    if column in best:
        text = f"{marks[0]}{text}{marks[1]}"
    elif column in second:
        text = f"{marks[2]}{text}{marks[3]}"
    unit = percent if change_unit(metric) == "%" else "pp"
    shown = []
    extra = () if table.paired_against in REFERENCES else (table.paired_against,)
    for ref in REFERENCES + extra:
        paired = table.paired(cell, metric, column) if ref == table.paired_against else None
        change = table.change(cell, metric, column, ref) if ref in REFERENCES else None
        if paired is not None:
            mark = "" if paired.measurable else f"{NO_DIFFERENCE} "
            versus = f"vs {ref} " if extra else ""
            shown.append(
                f"{versus}{mark}{paired.change:+.1f} {unit} [{paired.low:+.1f}, {paired.high:+.1f}]"
            )
        elif change is not None:
            shown.append(f"{change:+.1f} {unit}")
    if shown:
        text += f" ({', '.join(shown)})"
    return text


def to_markdown(table: Table) -> str:
    """GitHub Markdown: the caption, then one section per map."""
    lines = [f"Table: {table.caption}", ""]
    header = "| Scenario | Metric | " + " | ".join(table.columns) + " |"
    rule = "|---|---|" + "---|" * len(table.columns)
    for map_name in dict.fromkeys(c.map for c in table.cells):
        lines += [f"**{map_name}**", "", header, rule]
        for cell in (c for c in table.cells if c.map == map_name):
            for i, metric in enumerate(table.rows):
                entries = [
                    _entry(table, cell, metric, col, ("**", "**", "_", "_"))
                    for col in table.columns
                ]
                lines.append(
                    f"| {_scenario(cell) if i == 0 else ''} | {_label(metric)} | "
                    + " | ".join(entries)
                    + " |"
                )
        lines.append("")
    lines += [f"- {note}" for note in table.notes]
    return "\n".join(lines) + "\n"


def _latex_escape(text: str) -> str:
    return (
        text.replace("%", r"\%")
        .replace("_", r"\_")
        .replace("±", r"$\pm$")
        .replace(NO_DIFFERENCE, r"$\approx$")
    )


def to_latex(table: Table) -> str:
    """A booktabs ``table`` in the paper's layout; needs :data:`LATEX_PREAMBLE`."""
    n = len(table.columns)
    k = len(table.rows)
    lines = [
        "% preamble: " + LATEX_PREAMBLE.replace("\n", " "),
        r"\begin{table}[htbp]",
        r"\centering",
        rf"\caption{{{_latex_escape(table.caption)}}}",
        r"\begin{tabular}{@{}ll" + "c" * n + "@{}}",
        r"\toprule",
        r"\textbf{Scenario} & \textbf{Metric} & "
        + " & ".join(rf"\textbf{{{_latex_escape(c)}}}" for c in table.columns)
        + r" \\",
        r"\midrule",
    ]
    maps = list(dict.fromkeys(c.map for c in table.cells))
    for m, map_name in enumerate(maps):
        lines.append(rf"\multicolumn{{{n + 2}}}{{c}}{{\textit{{{_latex_escape(map_name)}}}}} \\")
        lines.append(r"\midrule")
        cells = [c for c in table.cells if c.map == map_name]
        for j, cell in enumerate(cells):
            for i, metric in enumerate(table.rows):
                scenario = (
                    rf"\multirow{{{k}}}{{*}}{{{_size(cell)}, "
                    rf"$\rho={cell.cav_penetration:.1f}$, {cell.style_mix}}}"
                    if i == 0
                    else ""
                )
                entries = [
                    _latex_escape(
                        _entry(table, cell, metric, col, ("<<B>>", "<</B>>", "<<U>>", "<</B>>"))
                    )
                    .replace("<<B>>", r"\textbf{")
                    .replace("<<U>>", r"\underline{")
                    .replace("<</B>>", "}")
                    for col in table.columns
                ]
                lines.append(
                    f"{scenario} & \\textit{{{_latex_escape(_label(metric))}}} & "
                    + " & ".join(entries)
                    + r" \\"
                )
            if j < len(cells) - 1:
                lines.append(rf"\cmidrule{{1-{n + 2}}}")
        lines.append(r"\bottomrule" if m == len(maps) - 1 else r"\midrule")
    lines += [r"\end{tabular}", r"\end{table}"]
    lines += [f"% {note}" for note in table.notes]
    return "\n".join(lines) + "\n"


def to_csv(table: Table) -> str:
    """Tidy CSV: one line per (cell, metric, policy); ``change`` in ``change_unit``
    (% or pp, :func:`change_unit`); ``best`` 1 best, 2 second best (within a backend)."""
    header = [
        *CELL_KEYS,
        "metric",
        "policy",
        "mean",
        "std",
        "n_episodes",
        "change",
        "change_same_mix",
        "change_unit",
        "best",
        "paired_against",
        "paired_change",
        "ci_low",
        "ci_high",
        "n_pairs",
        "measurable",
    ]
    rows = []
    for cell in table.cells:
        for metric in table.rows:
            best, second = table.marks(cell, metric)
            for col in table.columns:
                stat = table.stats.get((cell.key, metric, col))
                if stat is None:
                    continue
                change = table.change(cell, metric, col)
                change_mix = table.change(cell, metric, col, "same-mix")
                paired = table.paired(cell, metric, col)
                rows.append(
                    [
                        *cell.as_row().values(),
                        metric,
                        col,
                        repr(stat.mean),
                        repr(stat.std),
                        stat.n_episodes,
                        "" if change is None else repr(change),
                        "" if change_mix is None else repr(change_mix),
                        change_unit(metric),
                        1 if col in best else 2 if col in second else 0,
                        *(
                            ["", "", "", "", "", ""]
                            if paired is None
                            else [
                                table.paired_against,
                                repr(paired.change),
                                repr(paired.low),
                                repr(paired.high),
                                paired.n_pairs,
                                int(paired.measurable),
                            ]
                        ),
                    ]
                )
    return csv_text(header, rows)


def render_table(table: Table, fmt: str) -> str:
    if fmt not in FORMATS:
        raise EvaluationError(f"unknown table format {fmt!r}; use one of {', '.join(FORMATS)}")
    return {"markdown": to_markdown, "latex": to_latex, "csv": to_csv}[fmt](table)
