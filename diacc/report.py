"""Paper-style result tables (Tables II-III) from evaluation results directories.

One column per evaluated policy (one results directory each), and for every
grid cell three rows:

* **Speed (m/s)**: mean +- std over all vehicles and steps of all episodes,
  as in the paper (pooled exactly from each episode's mean, std and sample
  count); ``speed_std="episodes"`` gives mean +- std of the episode means
  instead.
* **p(WE) (%)**, **p(SCE) (%)**: mean +- std over episodes of the per-episode
  shares (population std, ddof = 0).

Each entry also shows its relative change against the ``pure-hdv`` column
(when one is given), ``(mean - mean_ref) / mean_ref``; the best value of a row
(highest speed, lowest shares, compared at the printed precision) is bold.
Output as Markdown, LaTeX (booktabs) or a tidy CSV.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from diacc.evaluate import EvaluationError, load_episodes
from diacc.grid import Cell

#: (key, row label, higher is better, scale for display)
METRICS = (
    ("speed", "Speed (m/s)", True, 1.0),
    ("p_we", "p(WE) (%)", False, 100.0),
    ("p_sce", "p(SCE) (%)", False, 100.0),
)
REFERENCE = "pure-hdv"
FORMATS = ("markdown", "latex", "csv")
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

    def reference(self, column: str) -> str | None:
        """The pure-HDV column a column is compared with: same backend first."""
        refs = [c for c in self.columns if self.policy[c] == REFERENCE]
        same = [c for c in refs if self.backend[c] == self.backend[column]]
        return (same or refs or [None])[0]

    def relative_change(self, cell: Cell, metric: str, column: str) -> float | None:
        """Percent change of the mean against the pure-HDV column (None if undefined)."""
        ref = self.reference(column)
        if ref is None or self.policy[column] == REFERENCE:
            return None
        a, b = self.stats.get((cell.key, metric, column)), self.stats.get((cell.key, metric, ref))
        if a is None or b is None or b.mean == 0 or not math.isfinite(b.mean):
            return None
        return 100.0 * (a.mean - b.mean) / b.mean

    def best(self, cell: Cell, metric: str) -> set[str]:
        """Columns holding the best value of a row, at the printed precision."""
        higher = next(m[2] for m in METRICS if m[0] == metric)
        values = {
            c: round(s.mean, 2)
            for c in self.columns
            if (s := self.stats.get((cell.key, metric, c))) and math.isfinite(s.mean)
        }
        if len(values) < 2:
            return set()
        target = max(values.values()) if higher else min(values.values())
        return {c for c, v in values.items() if v == target}


def _float(text: str) -> float:
    return float(text) if text not in ("", "nan") else float("nan")


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


def _share_stat(rows: list[dict[str, str]], key: str) -> Stat:
    values = 100.0 * np.array([_float(r[key]) for r in rows])  # (K,) percent
    return Stat(float(values.mean()), float(values.std()), len(rows))


def build_table(result_dirs: list[str | Path], speed_std: str = "samples") -> Table:
    """Collect the statistics of several results directories into one table."""
    if speed_std not in SPEED_STD:
        raise EvaluationError(f"unknown speed std {speed_std!r}; use one of {', '.join(SPEED_STD)}")
    if not result_dirs:
        raise EvaluationError("give at least one results directory")
    loaded = [(Path(d), *load_episodes(d)) for d in result_dirs]
    labels = [meta["policy"] for _, meta, _ in loaded]
    if len(set(labels)) < len(labels):  # same policy twice: tell them apart by backend, then dir
        labels = [f"{meta['policy']} ({meta['backend']})" for _, meta, _ in loaded]
    if len(set(labels)) < len(labels):
        labels = [f"{lab} [{d.name}]" for lab, (d, _, _) in zip(labels, loaded, strict=True)]
    stats: dict[tuple[str, str, str], Stat] = {}
    cells: dict[str, Cell] = {}
    notes: list[str] = []
    for label, (_, meta, rows) in zip(labels, loaded, strict=True):
        by_cell: dict[Cell, list[dict[str, str]]] = {}
        for row in rows:
            cell = Cell(
                row["map"], int(row["n_vehicles"]), float(row["cav_penetration"]), row["style_mix"]
            )
            by_cell.setdefault(cell, []).append(row)
        for cell, cell_rows in by_cell.items():
            cells[cell.key] = cell
            stats[(cell.key, "speed", label)] = _speed_stat(cell_rows, speed_std)
            stats[(cell.key, "p_we", label)] = _share_stat(cell_rows, "p_we")
            stats[(cell.key, "p_sce", label)] = _share_stat(cell_rows, "p_sce")
        first = rows[0]
        version = f", {first['sumo_version']}" if first.get("sumo_version") else ""
        per_cell = sorted({len(r) for r in by_cell.values()})
        episodes = "/".join(map(str, per_cell))
        notes.append(
            f"{label}: {meta['backend']} backend{version}, style preset "
            f"{first.get('style_preset', '?')}, {episodes} episodes per cell"
        )
    speed_note = (
        "speed: mean ± std over all vehicles and steps"
        if speed_std == "samples"
        else "speed: mean ± std of episode means"
    )
    notes.append(f"{speed_note}; p(WE), p(SCE): mean ± std over episodes")
    ordered = sorted(
        cells.values(), key=lambda c: (c.map, -c.cav_penetration, c.n_vehicles, c.style_mix)
    )
    return Table(
        labels,
        ordered,
        stats,
        notes,
        policy={lab: m["policy"] for lab, (_, m, _) in zip(labels, loaded, strict=True)},
        backend={lab: m["backend"] for lab, (_, m, _) in zip(labels, loaded, strict=True)},
    )


# ----------------------------------------------------------------------------- rendering
def _scenario(cell: Cell) -> str:
    return f"N={cell.n_vehicles}, rho={cell.cav_penetration:.1f}, {cell.style_mix}"


def _entry(
    table: Table, cell: Cell, metric: str, column: str, bold: tuple[str, str], percent: str = "%"
) -> str:
    stat = table.stats.get((cell.key, metric, column))
    if stat is None:
        return "—"
    text = f"{stat.mean:.2f} ± {stat.std:.2f}"
    if column in table.best(cell, metric):
        text = f"{bold[0]}{text}{bold[1]}"
    change = table.relative_change(cell, metric, column)
    if change is not None:
        text += f" ({change:+.1f}{percent})"
    return text


def to_markdown(table: Table) -> str:
    """GitHub Markdown: one section per map."""
    lines = []
    header = "| Scenario | Metric | " + " | ".join(table.columns) + " |"
    rule = "|---|---|" + "---|" * len(table.columns)
    for map_name in dict.fromkeys(c.map for c in table.cells):
        lines += [f"**{map_name}**", "", header, rule]
        for cell in (c for c in table.cells if c.map == map_name):
            for i, (metric, label, _, _) in enumerate(METRICS):
                entries = [_entry(table, cell, metric, col, ("**", "**")) for col in table.columns]
                lines.append(
                    f"| {_scenario(cell) if i == 0 else ''} | {label} | "
                    + " | ".join(entries)
                    + " |"
                )
        lines.append("")
    lines += [f"- {note}" for note in table.notes]
    return "\n".join(lines) + "\n"


def _latex_escape(text: str) -> str:
    return text.replace("%", r"\%").replace("_", r"\_").replace("±", r"$\pm$")


def to_latex(table: Table) -> str:
    """A booktabs ``tabular`` in the paper's layout (needs ``booktabs`` and ``multirow``)."""
    n = len(table.columns)
    lines = [
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
        for k, cell in enumerate(cells):
            for i, (metric, label, _, _) in enumerate(METRICS):
                scenario = (
                    rf"\multirow{{3}}{{*}}{{N={cell.n_vehicles}, "
                    rf"$\rho={cell.cav_penetration:.1f}$, {cell.style_mix}}}"
                    if i == 0
                    else ""
                )
                entries = [
                    _latex_escape(_entry(table, cell, metric, col, ("<<B>>", "<</B>>")))
                    .replace("<<B>>", r"\textbf{")
                    .replace("<</B>>", "}")
                    for col in table.columns
                ]
                lines.append(
                    f"{scenario} & \\textit{{{_latex_escape(label)}}} & "
                    + " & ".join(entries)
                    + r" \\"
                )
            if k < len(cells) - 1:
                lines.append(rf"\cmidrule{{1-{n + 2}}}")
        lines.append(r"\bottomrule" if m == len(maps) - 1 else r"\midrule")
    lines.append(r"\end{tabular}")
    lines += [f"% {note}" for note in table.notes]
    return "\n".join(lines) + "\n"


def to_csv(table: Table) -> str:
    """Tidy CSV: one line per (cell, metric, policy)."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(
        [
            "map",
            "n_vehicles",
            "cav_penetration",
            "style_mix",
            "metric",
            "policy",
            "mean",
            "std",
            "n_episodes",
            "rel_change_pct",
            "best",
        ]
    )
    for cell in table.cells:
        for metric, _, _, _ in METRICS:
            best = table.best(cell, metric)
            for col in table.columns:
                stat = table.stats.get((cell.key, metric, col))
                if stat is None:
                    continue
                change = table.relative_change(cell, metric, col)
                writer.writerow(
                    [
                        cell.map,
                        cell.n_vehicles,
                        cell.cav_penetration,
                        cell.style_mix,
                        metric,
                        col,
                        repr(stat.mean),
                        repr(stat.std),
                        stat.n_episodes,
                        "" if change is None else repr(change),
                        int(col in best),
                    ]
                )
    return buffer.getvalue()


def render_table(table: Table, fmt: str) -> str:
    if fmt not in FORMATS:
        raise EvaluationError(f"unknown table format {fmt!r}; use one of {', '.join(FORMATS)}")
    return {"markdown": to_markdown, "latex": to_latex, "csv": to_csv}[fmt](table)
