"""Markdown, LaTeX (booktabs, multirow: :data:`LATEX_PREAMBLE`) and tidy CSV output of a
:class:`~diacc.experiments.report.table.Table`.

Emphasis follows the paper's Tables II/III: per row the best value is bold and the
second best underlined (italic in Markdown), as :meth:`Table.marks
<diacc.experiments.report.table.Table.marks>` ranks them.
"""

from __future__ import annotations

from diacc.experiments.evaluate import EvaluationError, csv_text
from diacc.experiments.grid import CELL_KEYS, Cell
from diacc.experiments.report.table import (
    METRICS,
    NO_DIFFERENCE,
    REFERENCES,
    Table,
    change_unit,
)

FORMATS = ("markdown", "latex", "csv")
#: What a LaTeX document needs for :func:`to_latex`'s output.
LATEX_PREAMBLE = "\\usepackage{booktabs}\n\\usepackage{multirow}"


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
