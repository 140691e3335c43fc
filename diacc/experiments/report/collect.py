"""Tables from evaluation results directories: per grid cell and column, the statistics
of each row's metric (:data:`~diacc.experiments.report.table.METRICS`) over the episodes of
``episodes.csv``, and the per-episode values the paired changes resample.

Speed is the mean +- std over all vehicles and steps of all episodes, as in the paper,
pooled exactly from each episode's mean, std and sample count (``speed_std="episodes"``:
mean +- std of the episode means instead); every other row is the mean +- std over
episodes (population std, ddof = 0) of the episodes where it is defined.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np

from diacc.experiments.evaluate import EvaluationError, load_episodes
from diacc.experiments.grid import Cell
from diacc.experiments.paired import EpisodeValues
from diacc.experiments.report.table import (
    CHANGE_RULE,
    DEFAULT_ROWS,
    FLOW_ROWS,
    METRICS,
    PAIRED_REFERENCE,
    RANKING_RULE,
    REFERENCE,
    REFERENCES,
    Stat,
    Table,
    interval_rule,
)
from diacc.experiments.sametraffic import check_same_traffic

#: What a speed entry's std spreads over: all speed samples (as the paper), or episode means.
SPEED_STD = ("samples", "episodes")


#: Row key naming the training run of an episode where a column pools several runs
#: (its paired intervals resample the runs too: :mod:`diacc.experiments.paired`).
TRAINING_RUN = "training_run"


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
    speed weighted by its sample count where the table pools samples; the training run
    of each episode where rows pool several (:data:`TRAINING_RUN`)."""
    if "seed" not in rows[0] or column not in rows[0]:
        return None
    weight = np.ones(len(rows))  # (K,)
    if metric == "speed" and speed_std == "samples":
        weight = np.array([float(r["n_speed_samples"]) for r in rows])
    return EpisodeValues(
        seed=np.array([int(r["seed"]) for r in rows], dtype=np.int64),
        value=scale * np.array([_float(r[column]) for r in rows]),
        weight=weight,
        run=np.array([int(r[TRAINING_RUN]) for r in rows]) if TRAINING_RUN in rows[0] else None,
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
    against the ``paired_against`` column carry their interval: the column of a policy
    name (same-mix, heuristic), or of one of ``result_dirs`` (to pair policies that share
    a name, e.g. two checkpoints). Where any episode had a collision, the collision row
    is shown even if ``rows`` leaves it out."""
    _check_options(speed_std, rows)
    if not result_dirs:
        raise EvaluationError("give at least one results directory")
    loaded = [(Path(d), *load_episodes(d)) for d in result_dirs]
    policies = {meta["policy"] for _, meta, _ in loaded}
    by_dir = [i for i, (d, _, _) in enumerate(loaded) if _same_dir(d, paired_against)]
    if paired_against not in policies and paired_against != PAIRED_REFERENCE and not by_dir:
        raise EvaluationError(
            f"--paired-against {paired_against}: neither a policy of the results directories "
            f"({', '.join(sorted(policies))}) nor one of the directories"
        )
    if "collision" not in rows and any(
        float(row.get("collision") or 0) > 0 for _, _, episodes in loaded for row in episodes
    ):
        rows = (*rows, "collision")  # a crash is never left out of a table
    table = table_from_results(loaded, speed_std, rows)
    if by_dir and paired_against not in policies:
        paired_against = table.columns[by_dir[0]]  # the directory's column label
    if paired_against != PAIRED_REFERENCE:
        notes = [
            interval_rule(paired_against) if n == interval_rule(PAIRED_REFERENCE) else n
            for n in table.notes
        ]
        if interval_rule(paired_against) not in notes:
            notes.insert(-2, interval_rule(paired_against))
        table = dataclasses.replace(table, paired_against=paired_against, notes=notes)
    return table


def _same_dir(directory: Path, text: str) -> bool:
    """Whether ``text`` names ``directory`` (as given, or as the same path resolved)."""
    return Path(text).exists() and Path(text).resolve() == directory.resolve()


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


def _distinct_names(dirs: list[Path]) -> list[str]:
    """The shortest trailing parts of each directory's path that tell them apart
    (``q3600`` twice becomes ``same-mix/q3600`` and ``heuristic/q3600``)."""
    parts = [Path(d).resolve().parts for d in dirs]
    for depth in range(1, max(map(len, parts)) + 1):
        names = ["/".join(p[-depth:]) for p in parts]
        if len(set(names)) == len(names):
            return names
    return [str(d) for d in dirs]  # the same directory twice: nothing tells them apart


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
        names = _distinct_names([d for d, _, _ in loaded])
        labels = [f"{lab} [{n}]" for lab, n in zip(labels, names, strict=True)]
    check_same_traffic([(lab, m, r) for lab, (_, m, r) in zip(labels, loaded, strict=True)])
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
