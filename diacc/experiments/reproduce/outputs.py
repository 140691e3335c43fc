"""Tables II/III, figures and the transfer report of ``diacc reproduce``, from its files.

Every number comes from the evaluation files (``eval/<backend>/<policy>/episodes.csv``
and ``speeds.csv.gz``) and the runs' ``progress.jsonl``; nothing is carried
over in memory from the stages, so the outputs can be rebuilt at any time.

* **Columns**: the two baselines, then one column per variant (and per
  ``--sweep`` setting, labelled with its values) that pools the
  episodes of all its seeds (and, per cell, of the checkpoints trained on a
  map with that cell's lane reduction). The table code is
  :mod:`diacc.experiments.report`'s (:func:`~diacc.experiments.report.table_from_results`), so
  emphasis, reference column and captions follow ``diacc table``.
* **Tables**: Table II = the ``train`` grid, Table III = the ``zero-shot``
  grid (the paper's five zero-shot rows per test map; ``table3-product`` for
  the ``zero-shot-product`` grid when asked for), one table per evaluation
  backend, Markdown and LaTeX.
* **Figures**: training curves per training map (mean and +-1 std band over
  seeds, :func:`diacc.experiments.plots.plot_curves`) and per-segment speed box plots and
  KDEs per backend and map (:func:`diacc.experiments.plots.draw_speeds`).
* **Transfer**: SUMO speed of pure HDV, of diacc trained on the training
  backend, and of diacc trained on SUMO; the share of the SUMO-trained
  policy's speed gain that the other keeps.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from diacc.experiments.evaluate import EPISODES_FILE, SPEEDS_FILE, csv_text, load_episodes
from diacc.experiments.grid import CELL_KEYS, Cell
from diacc.experiments.plots import PlotError
from diacc.experiments.report import FLOW_ROWS, TRAINING_RUN
from diacc.experiments.reproduce.plan import (
    BASELINE_COLUMNS,
    TRANSFER_BACKEND,
    TRANSFER_VARIANT,
    Plan,
    RunSpec,
    reduction_of,
)
from diacc.experiments.reproduce.stages import row_cell_key
from diacc.fileio import atomic_write
from diacc.sim.maps import SEGMENT_KINDS

#: Table rows: the paper's three, the share of episodes ending in a collision, the flow rows.
TABLE_ROWS = ("speed", "p_we", "p_sce", "collision", *FLOW_ROWS)
TABLES = {"train": "table2", "zero-shot": "table3", "zero-shot-product": "table3-product"}
TABLE_TITLES = {
    "train": "Table II (training grid)",
    "zero-shot": "Table III (the paper's zero-shot rows)",
    "zero-shot-product": "Table III, product grid (zero-shot-product)",
}
TRANSFER_MD = "transfer.md"
TRANSFER_CSV = "transfer.csv"


class _Results:
    """Episode rows of the evaluation directories, each read once."""

    def __init__(self, plan: Plan) -> None:
        self.plan = plan
        self._cache: dict[Path, tuple[dict, list[dict[str, str]]]] = {}
        self._speeds: dict[Path, dict[str, dict[str, np.ndarray]]] = {}

    def load(self, backend: str, policy: str) -> tuple[dict, list[dict[str, str]]]:
        path = self.plan.config.out_dir / "eval" / backend / policy
        if path not in self._cache:
            self._cache[path] = load_episodes(path)
        return self._cache[path]

    def speeds(self, backend: str, policy: str) -> dict[str, dict[str, np.ndarray]]:
        """Map -> segment kind -> speed samples of one directory, read once."""
        from diacc.experiments.plots import load_speeds_by_map

        path = self.plan.config.out_dir / "eval" / backend / policy
        if path not in self._speeds:
            self._speeds[path] = load_speeds_by_map(path)[1]
        return self._speeds[path]

    def column(
        self, backend: str, label: str, members: list[tuple[str, RunSpec | None]], cells
    ) -> tuple[Path, dict, list[dict[str, str]]]:
        """(name, meta, rows) of one table column pooling ``members`` on ``cells``.

        A member is (policy directory name, its run or None); a run contributes
        only the cells of its map's lane reduction.
        """
        rows, metas = [], []
        for index, (policy, run) in enumerate(members):
            meta, member_rows = self.load(backend, policy)
            keys = {
                c.key for c in cells if run is None or reduction_of(c.map) == reduction_of(run.map)
            }
            # which run an episode is from: the paired intervals resample runs too
            rows += [
                dict(r, **{TRAINING_RUN: index}) for r in member_rows if row_cell_key(r) in keys
            ]
            metas.append(meta)
        meta = dict(metas[0], policy=label)
        if "trained_steps" in meta:
            meta["trained_steps"] = min(m["trained_steps"] for m in metas)
            meta["checkpoint"] = f"{len(metas)} checkpoints"
        return Path(label), meta, rows


def _columns(plan: Plan, results: _Results, backend: str, cells) -> list:
    columns = [results.column(backend, p, [(p, None)], cells) for p in BASELINE_COLUMNS]
    for label, members in _learned_columns(plan).items():
        columns.append(results.column(backend, label, members, cells))
    return columns


def _learned_columns(plan: Plan) -> dict[str, list[tuple[str, RunSpec]]]:
    """Column label -> its (run name, run) members: one column per variant and setting,
    pooling seeds (and the training maps, each on the cells of its lane reduction)."""
    columns: dict[str, list[tuple[str, RunSpec]]] = {}
    for variant in plan.config.variants:
        for run in plan.runs:
            if run.variant == variant and run.backend == plan.config.train_backend:
                columns.setdefault(run.column, []).append((run.name, run))
    return columns


def _pool_note(plan: Plan) -> str:
    b = plan.config.budget
    return (
        f"learned columns pool {len(b.seeds)} seed(s) x {b.episodes_per_cell} episode(s) per "
        f"cell, from checkpoints trained on {plan.config.train_backend} on the map with the "
        f"cell's lane reduction ({', '.join(b.maps)}), {plan.config.actions} actions"
    )


def write_tables(plan: Plan, results: _Results | None = None) -> list[Path]:
    """``tables/table2.{md,tex}`` and ``tables/table3.{md,tex}`` for the grids evaluated."""
    from diacc.experiments.report import table_from_results, to_latex, to_markdown

    results = results or _Results(plan)
    out = plan.config.out_dir / "tables"
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for grid, cells in plan.grid_cells.items():
        md, tex = [f"# {TABLE_TITLES[grid]}", ""], []
        for backend in plan.config.backends:
            table = table_from_results(_columns(plan, results, backend, cells), rows=TABLE_ROWS)
            table.notes.append(_pool_note(plan))
            table.caption = f"{TABLE_TITLES[grid]}, {backend} backend. {table.caption}"
            md += [f"## {backend} backend", "", to_markdown(table)]
            tex += [f"% {TABLE_TITLES[grid]}, {backend} backend", to_latex(table)]
        for suffix, text in ((".md", "\n".join(md)), (".tex", "\n".join(tex))):
            path = out / f"{TABLES[grid]}{suffix}"
            atomic_write(path, text)
            written.append(path)
    return written


# ----------------------------------------------------------------------------- figures
def _pooled_speeds(
    results: _Results, backend: str, members: list[tuple[str, RunSpec | None]], map_name: str
) -> dict[str, np.ndarray]:
    """Segment kind -> speed samples on one map, pooled over ``members`` (as in the tables)."""
    parts: dict[str, list[np.ndarray]] = {k: [] for k in SEGMENT_KINDS}
    for policy, run in members:
        if run is not None and reduction_of(run.map) != reduction_of(map_name):
            continue
        by_map = results.speeds(backend, policy)
        if map_name not in by_map:
            raise PlotError(f"eval/{backend}/{policy} has no speed samples on map {map_name}")
        for kind, samples in by_map[map_name].items():
            parts[kind].append(samples)
    return {k: np.concatenate(v) if v else np.zeros(0) for k, v in parts.items()}


def write_figures(plan: Plan, results: _Results | None = None) -> list[Path]:
    """Training curves per training map; speed distributions per backend and evaluated map."""
    from diacc.console import plural
    from diacc.experiments.plots import draw_speeds, plot_curves

    results = results or _Results(plan)
    cfg = plan.config
    out = cfg.out_dir / "figures"
    written = []
    for map_name in cfg.budget.maps:
        runs = [plan.run_dir(r) for r in plan.runs if r.map == map_name]
        written += plot_curves(runs, out / f"curves-{Path(map_name).stem}")
    cell_maps = dict.fromkeys(c.map for cells in plan.grid_cells.values() for c in cells)
    for backend in cfg.backends:
        for map_name in cell_maps:
            columns = [
                (p, _pooled_speeds(results, backend, [(p, None)], map_name))
                for p in BASELINE_COLUMNS
            ]
            for label, members in _learned_columns(plan).items():
                columns.append((label, _pooled_speeds(results, backend, members, map_name)))
            title = f"{map_name} on {backend}: {plural(len(cfg.budget.seeds), 'seed')} pooled"
            written += draw_speeds(columns, out / f"speeds-{backend}-{map_name}", title)
    return written


# ----------------------------------------------------------------------------- transfer
@dataclass(frozen=True)
class TransferRow:
    """One training cell of the transfer experiment, speeds on SUMO in m/s."""

    cell: Cell
    pure_hdv_speed_mps: float
    source_speed_mps: float  # trained on the training backend
    target_speed_mps: float  # trained on SUMO

    @property
    def source_gain_mps(self) -> float:
        return self.source_speed_mps - self.pure_hdv_speed_mps

    @property
    def target_gain_mps(self) -> float:
        return self.target_speed_mps - self.pure_hdv_speed_mps

    @property
    def kept_share(self) -> float | None:
        """Gain of the transferred policy over the gain of the SUMO-trained one; None if that
        gain is <= 0 (nothing to keep, and the ratio's sign would mislead)."""
        if not self.target_gain_mps > 0:
            return None
        return self.source_gain_mps / self.target_gain_mps


def transfer_rows(plan: Plan, results: _Results | None = None) -> list[TransferRow]:
    """Speeds on SUMO of pure HDV and of both diacc trainings, per transfer cell."""
    from diacc.experiments.report import table_from_results

    results = results or _Results(plan)
    source, target = (list(side) for side in zip(*plan.transfer_pairs, strict=True))
    labels = ("pure-hdv", "source", "target")
    members = ([("pure-hdv", None)], [(r.name, r) for r in source], [(r.name, r) for r in target])
    columns = [
        results.column(TRANSFER_BACKEND, label, mine, plan.transfer_cells)
        for label, mine in zip(labels, members, strict=True)
    ]
    table = table_from_results(columns, rows=("speed",))
    return [
        TransferRow(cell, *(table.stats[(cell.key, "speed", lab)].mean for lab in labels))
        for cell in plan.transfer_cells
    ]


def _pct(gain: float, base: float) -> str:
    return f"{100 * gain / base:+.1f} %" if base > 0 else "n/a"


def write_transfer(plan: Plan, results: _Results | None = None) -> list[Path]:
    """``transfer.md`` and ``transfer.csv`` (see :class:`TransferRow`)."""
    rows = transfer_rows(plan, results)
    cfg, b = plan.config, plan.config.budget
    src = cfg.train_backend
    md = [
        f"# Sim-to-sim transfer: {TRANSFER_VARIANT} trained on {src} vs on {TRANSFER_BACKEND}, "
        f"both evaluated on {TRANSFER_BACKEND}",
        "",
        f"Budget {b.name}: {b.steps_per_run:,} env steps per run, {b.n_envs} envs, seeds "
        f"{', '.join(map(str, b.seeds))} (each seed trained on both backends), "
        f"{b.episodes_per_cell} episode(s) per cell and seed, pooled over seeds; HDV style "
        f"preset {cfg.style_preset}.",
        "",
        "Speed: mean over all vehicles and steps on SUMO (m/s). Gain: speed minus the "
        "pure-HDV speed of the same cell and episodes. Kept share = gain of the "
        f"{src}-trained policy / gain of the {TRANSFER_BACKEND}-trained policy: how much "
        f"of what training on {TRANSFER_BACKEND} achieves survives the change of simulator.",
        "",
        f"| cell | pure HDV | {TRANSFER_VARIANT} ({src}-trained) | gain | "
        f"{TRANSFER_VARIANT} ({TRANSFER_BACKEND}-trained) | gain | kept share |",
        "|---|---|---|---|---|---|---|",
    ]
    why = []
    for r in rows:
        kept = "n/a" if r.kept_share is None else f"{r.kept_share:.2f}"
        md.append(
            f"| {r.cell.key} | {r.pure_hdv_speed_mps:.2f} | {r.source_speed_mps:.2f} | "
            f"{r.source_gain_mps:+.2f} ({_pct(r.source_gain_mps, r.pure_hdv_speed_mps)}) | "
            f"{r.target_speed_mps:.2f} | {r.target_gain_mps:+.2f} "
            f"({_pct(r.target_gain_mps, r.pure_hdv_speed_mps)}) | {kept} |"
        )
        if r.kept_share is None:
            why.append(
                f"- {r.cell.key}: kept share n/a because the {TRANSFER_BACKEND}-trained policy "
                f"is not faster than pure HDV (gain {r.target_gain_mps:+.2f} m/s <= 0): there "
                "is no gain to keep, and a ratio of two losses would read as success."
            )
    md += ["", *why] if why else []
    out = cfg.out_dir
    atomic_write(out / TRANSFER_MD, "\n".join(md) + "\n")
    header = [
        *CELL_KEYS,
        "pure_hdv_speed_mps",
        f"{src}_trained_speed_mps",
        f"{TRANSFER_BACKEND}_trained_speed_mps",
        f"{src}_trained_gain_mps",
        f"{TRANSFER_BACKEND}_trained_gain_mps",
        "kept_share",
    ]
    csv_rows = [
        [
            *r.cell.as_row().values(),
            repr(r.pure_hdv_speed_mps),
            repr(r.source_speed_mps),
            repr(r.target_speed_mps),
            repr(r.source_gain_mps),
            repr(r.target_gain_mps),
            "n/a" if r.kept_share is None else repr(r.kept_share),
        ]
        for r in rows
    ]
    atomic_write(out / TRANSFER_CSV, csv_text(header, csv_rows))
    return [out / TRANSFER_MD, out / TRANSFER_CSV]


# ----------------------------------------------------------------------------- all of it
def inputs_fingerprint(plan: Plan) -> str:
    """Hash of everything the outputs are computed from (files and plan)."""
    digest = hashlib.sha256(json.dumps(asdict(plan.config), default=str).encode())
    files = [plan.eval_dir(j) / name for j in plan.jobs for name in (EPISODES_FILE, SPEEDS_FILE)]
    files += [plan.run_dir(r) / "progress.jsonl" for r in plan.runs]
    for path in files:
        digest.update(str(path).encode())
        digest.update(path.read_bytes() if path.exists() else b"<missing>")
    return digest.hexdigest()


def write_outputs(plan: Plan) -> list[Path]:
    """Tables, figures and (if planned) the transfer report; returns the files written."""
    results = _Results(plan)
    written = write_tables(plan, results)
    written += write_figures(plan, results)
    if plan.transfer_pairs:
        written += write_transfer(plan, results)
    return written
