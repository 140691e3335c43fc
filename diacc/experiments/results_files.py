"""The files of an evaluation's results directory: written, checked, merged and read.

The layout is :mod:`diacc.experiments.evaluate`'s (its module docstring): one
pair of files per finished cell, written atomically once all its episodes are
in, merged into the directory's ``episodes.csv`` and ``speeds.csv.gz``. A cell
whose files do not add up is reported and removed, so that it is recomputed.
"""

from __future__ import annotations

import csv
import gzip
import io
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from diacc.envs.metrics import SpeedSamples
from diacc.errors import DiaccError
from diacc.experiments.grid import CELL_KEYS, Cell, make_cell
from diacc.fileio import atomic_write
from diacc.runlog import log
from diacc.tomlfile import read_json_object

META_FILE = "meta.json"
EPISODES_FILE = "episodes.csv"
SPEEDS_FILE = "speeds.csv.gz"
CELLS_DIR = "cells"
#: Rows of results that came as merged files only (:func:`adopt_merged_only`), in CELLS_DIR.
MERGED_ONLY_FILE = "merged-only.csv"
LOG_FILE = "eval.log"
#: Columns of the speed-sample files.
SPEED_COLUMNS = (
    "policy",
    "backend",
    *CELL_KEYS,
    "episode",
    "vehicle",
    "step",
    "time_s",
    "speed_mps",
    "segment_kind",
    "is_cav",
)


class EvaluationError(DiaccError, ValueError):
    """Bad evaluation input (episodes, results directory...); one line."""


@dataclass
class EpisodeResult:
    """One evaluated episode: its CSV row, its speed samples and the policy's action counts."""

    cell: Cell
    episode: int
    row: dict
    speeds: SpeedSamples
    picked: np.ndarray  # (A,) actions the policy picked for living CAVs (EpisodeDriver.picked)


def csv_text(columns: list[str] | tuple[str, ...], rows: list) -> str:
    """CSV text of a header and rows, lines ending in ``\n`` on every platform: the one
    writer of the results files and of the tables and reports made from them, so that
    they all diff and hash the same everywhere."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(columns)
    writer.writerows(rows)
    return buffer.getvalue()


def _gzip(data: bytes) -> bytes:
    out = io.BytesIO()
    with gzip.GzipFile(fileobj=out, mode="wb", mtime=0) as fh:  # mtime 0: same bytes every run
        fh.write(data)
    return out.getvalue()


def speed_rows(result: EpisodeResult) -> list[tuple]:
    """Rows of :data:`SPEED_COLUMNS` for one episode."""
    prefix = (
        result.row["policy"],
        result.row["backend"],
        *result.cell.as_row().values(),
        result.episode,
    )
    return [prefix + r for r in result.speeds.rows()]


def write_cell(out_dir: Path, cell: Cell, results: list[EpisodeResult]) -> None:
    """Write one finished cell (speeds first: the episodes file marks it done)."""
    results = sorted(results, key=lambda r: r.episode)
    cells_dir = out_dir / CELLS_DIR
    cells_dir.mkdir(parents=True, exist_ok=True)
    speeds = [row for r in results for row in speed_rows(r)]
    speeds_bytes = _gzip(csv_text(SPEED_COLUMNS, speeds).encode())
    atomic_write(cells_dir / f"{cell.file_key}.speeds.csv.gz", speeds_bytes)
    columns = list(results[0].row)
    atomic_write(
        cells_dir / f"{cell.file_key}.episodes.csv",
        csv_text(columns, [[r.row[c] for c in columns] for r in results]).encode(),
    )


def read_csv(path: Path) -> list[dict[str, str]]:
    """Rows of a (possibly gzipped) CSV file as dicts of strings."""
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "rt", newline="") as fh:
        return list(csv.DictReader(fh))


def check_cell_files(out_dir: Path, key: str) -> tuple[list[int], str | None]:
    """(episode numbers, None) of a cell's files, or ([], why) if they are damaged.

    No episodes file means the cell is not done (it is written last); an
    episodes file whose rows, speeds file or sample count do not add up
    means a damaged (truncated, edited, half-copied) cell.
    """
    episodes_path = out_dir / CELLS_DIR / f"{key}.episodes.csv"
    speeds_path = out_dir / CELLS_DIR / f"{key}.speeds.csv.gz"
    if not episodes_path.exists():
        return [], None
    try:
        rows = read_csv(episodes_path)
        if not rows or any(None in r or None in r.values() for r in rows):
            raise ValueError(f"{episodes_path.name} has missing or extra fields")
        episodes = sorted(int(r["episode"]) for r in rows)
        n_samples = sum(int(r["n_speed_samples"]) for r in rows)
        if not speeds_path.exists():
            raise ValueError(f"{speeds_path.name} is missing")
        lines = gzip.decompress(speeds_path.read_bytes()).decode().splitlines()
        if not lines or lines[0] != ",".join(SPEED_COLUMNS) or len(lines) - 1 != n_samples:
            raise ValueError(f"{speeds_path.name} does not hold the {n_samples} speed samples")
    except (OSError, EOFError, ValueError, KeyError, zlib.error, csv.Error) as exc:
        return [], str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return episodes, None


def drop_if_damaged(out_dir: Path, key: str) -> list[int]:
    """Episodes of an intact cell; a damaged cell is reported and its files removed."""
    episodes, damage = check_cell_files(out_dir, key)
    if damage is not None:
        log.warning(
            "results cell %s in %s is damaged (%s); its files were removed and it is recomputed",
            key,
            out_dir,
            damage,
        )
        for suffix in (".episodes.csv", ".speeds.csv.gz"):
            (out_dir / CELLS_DIR / f"{key}{suffix}").unlink(missing_ok=True)
    return episodes


def cell_id(values: dict) -> tuple:
    """Which cell a results row (or a :class:`Cell`'s ``as_row`` plus ``inflow_vph``)
    belongs to, normalised so that text read back and values written compare equal."""
    return (
        values["map"],
        int(values["n_vehicles"]),
        float(values["cav_penetration"]),
        values["style_mix"],
        float(values.get("inflow_vph") or 0.0),
    )


def adopt_merged_only(out_dir: Path) -> None:
    """Keep the rows of a directory that holds merged results only (committed results
    leave ``cells/`` and the speed samples out) in ``cells/merged-only.csv``, so that a run
    over it counts their cells as done and keeps their rows when it merges new cells."""
    cells_dir = out_dir / CELLS_DIR
    if cells_dir.exists() or not (out_dir / EPISODES_FILE).exists():
        return
    rows = read_csv(out_dir / EPISODES_FILE)
    if rows:  # kept rows are read back as cells: checked as any reader checks them
        check_episode_rows(out_dir / EPISODES_FILE, rows)
    cells_dir.mkdir()
    atomic_write(cells_dir / MERGED_ONLY_FILE, (out_dir / EPISODES_FILE).read_bytes())
    log.info("%s holds merged results only: their cells are kept as done", out_dir)


def merged_only_episodes(out_dir: Path) -> dict[tuple, list[int]]:
    """Cell id -> episode numbers of the cells kept by :func:`adopt_merged_only` that
    have no per-cell files of their own."""
    _, rows = _merged_only_rows(out_dir)
    found: dict[tuple, list[int]] = {}
    for row in rows:
        found.setdefault(cell_id(row), []).append(int(row["episode"]))
    return {key: sorted(episodes) for key, episodes in found.items()}


def _merged_only_rows(out_dir: Path) -> tuple[list[str] | None, list[dict[str, str]]]:
    """(header, rows) of ``cells/merged-only.csv`` whose cell has no per-cell files."""
    path = out_dir / CELLS_DIR / MERGED_ONLY_FILE
    if not path.exists():
        return None, []
    cell_files = (out_dir / CELLS_DIR).glob("*.episodes.csv")
    in_cells = {cell_id(row) for p in cell_files for row in read_csv(p)}
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        rows = [r for r in reader if cell_id(r) not in in_cells]
        return reader.fieldnames, rows


def merge_cells(out_dir: Path) -> None:
    """Rebuild ``episodes.csv`` and ``speeds.csv.gz`` from every intact finished cell and
    the kept merged-only rows (:func:`adopt_merged_only`; they have no speed samples)."""
    cells_dir = out_dir / CELLS_DIR
    episode_files = [
        p
        for p in sorted(cells_dir.glob("*.episodes.csv"))
        if drop_if_damaged(out_dir, p.name.removesuffix(".episodes.csv"))
    ]
    header, kept = _merged_only_rows(out_dir)
    if not episode_files:
        return
    rows = [list(r.values()) for r in kept]
    for path in episode_files:
        with open(path, newline="") as fh:
            reader = csv.reader(fh)
            file_header = next(reader)
            header = header or file_header
            if file_header != header:
                raise EvaluationError(
                    f"{path} has other columns than the other cells; "
                    "re-run it into a fresh results directory"
                )
            rows += list(reader)
    atomic_write(out_dir / EPISODES_FILE, csv_text(header, rows).encode())
    parts = []
    for path in episode_files:
        speeds = path.with_name(path.name.replace(".episodes.csv", ".speeds.csv.gz"))
        body = gzip.decompress(speeds.read_bytes()).decode()
        parts.append(body if not parts else body.split("\n", 1)[1])
    atomic_write(out_dir / SPEEDS_FILE, _gzip("".join(parts).encode()))


def load_episodes(out_dir: str | Path) -> tuple[dict, list[dict[str, str]]]:
    """(meta, episode rows) of a results directory; one-line error if there are none."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise EvaluationError(f"results directory {out_dir} does not exist")
    path = out_dir / EPISODES_FILE
    if not (out_dir / META_FILE).exists() or not path.exists():
        raise EvaluationError(
            f"results directory {out_dir} holds no evaluation results "
            f"(no {EPISODES_FILE}); run `diacc eval --out {out_dir}` first"
        )
    rows = read_csv(path)
    if not rows:
        raise EvaluationError(f"results directory {out_dir} has an empty {EPISODES_FILE}")
    check_episode_rows(path, rows)
    meta = read_json_object(out_dir / META_FILE, EvaluationError)
    return check_meta(out_dir / META_FILE, meta), rows


def check_episode_rows(path: Path, rows: list[dict[str, str]]) -> None:
    """One-line :class:`EvaluationError` unless ``rows`` (of ``path``) are what the readers
    index: the :data:`REQUIRED_COLUMNS`, numbers where numbers belong, whole ones in the
    :data:`_WHOLE_COLUMNS`, and cells that exist."""
    missing = [c for c in REQUIRED_COLUMNS if c not in rows[0]]
    if missing:
        raise EvaluationError(
            f"{path} has no {missing[0]!r} column; the file is damaged: run `diacc eval` again "
            "into a fresh --out"
        )
    _check_numbers(path, rows)
    checked = set()
    for line, row in enumerate(rows, start=2):
        values = _cell_values(row, f"{path}:{line}")
        if tuple(values.items()) not in checked:  # a map loaded and placed once per cell
            make_cell(values, f"{path}:{line}")
            checked.add(tuple(values.items()))


#: What the readers take from ``meta.json``: its required fields, and the types of these
#: and of the optional ones they use (captions, budgets, settings).
_META_REQUIRED = ("policy", "backend")
_META_TYPES = {
    "policy": (str, "text"),
    "backend": (str, "text"),
    "settings": (dict, "a table"),
    "checkpoint": (str, "text"),
    "update": (int, "a whole number"),
    "trained_steps": (int, "a whole number"),
    "total_steps": (int, "a whole number"),
}


def check_meta(path: Path, meta: dict) -> dict:
    """``meta`` (read from ``path``) if it names policy and backend as text and its other
    known fields have their types; else a one-line :class:`EvaluationError`."""
    for key in _META_REQUIRED:
        if key not in meta:
            raise EvaluationError(f"{path} names no {key!r}; the file is damaged")
    for key, (kind, word) in _META_TYPES.items():
        value = meta.get(key)
        if key in meta and (not isinstance(value, kind) or isinstance(value, bool)):
            raise EvaluationError(f"{path}: {key!r} is {value!r}, not {word}; the file is damaged")
    return meta


#: Columns of episodes.csv that hold text; every other one holds a number (or is empty).
_TEXT_COLUMNS = {
    "policy",
    "backend",
    "sumo_version",
    "style_preset",
    "map",
    "style_mix",
    "psar",
    "stream",
}


#: Columns every reader of ``episodes.csv`` indexes without asking: the cell, the policy,
#: and the speed entry, pooled from each episode's mean, std and sample count.
REQUIRED_COLUMNS = (
    *CELL_KEYS,
    "policy",
    "backend",
    "episode",
    "mean_speed_mps",
    "std_speed_mps",
    "n_speed_samples",
)
#: Columns of whole numbers (counts, episode numbers, seeds), read back with ``int``.
_WHOLE_COLUMNS = {
    "n_vehicles",
    "episode",
    "seed",
    "n_cavs",
    "steps",
    "collision",
    "n_speed_samples",
    "n_collisions",
    "n_hdv_collisions",
    "n_vehicles_seen",
    "psar_decisions",
}


def _check_numbers(path: Path, rows: list[dict[str, str]]) -> None:
    """One-line :class:`EvaluationError` naming the first field that is not a number (or,
    in :data:`_WHOLE_COLUMNS`, not a whole one: a seed of nan pairs with nothing)."""
    for line, row in enumerate(rows, start=2):
        for column, text in row.items():
            if column in _TEXT_COLUMNS or not text:
                continue
            try:
                number = float(text)
            except (TypeError, ValueError):
                number = None
            whole = column not in _WHOLE_COLUMNS or (number is not None and number.is_integer())
            if number is None or not whole:
                what = "a number" if number is None else "a whole number"
                raise EvaluationError(
                    f"{path}:{line}: field {column!r} is not {what} ({text!r}); the file is "
                    "damaged: run `diacc eval` again into a fresh --out"
                )


def _cell_values(row: dict[str, str | None], source: str) -> dict:
    """The cell keys of an ``episodes.csv`` row, as :func:`make_cell` takes them.

    A demand cell (``inflow_vph`` > 0) is given by its inflow, not its vehicle
    count: the count follows from the inflow, and rebuilt as a release the
    cell's hundreds of vehicles do not fit the map.
    """
    missing = [k for k in CELL_KEYS if row.get(k) is None]
    if missing:
        raise EvaluationError(f"{source}: no {missing[0]!r} field; the file is damaged")
    values = {"map": row["map"], "style_mix": row["style_mix"]}
    values["cav_penetration"] = float(row["cav_penetration"])  # a number (_check_numbers)
    inflow = float(row.get("inflow_vph") or 0.0)
    if inflow:  # with its timing where set (older files: none, the defaults)
        timing = {k: float(row[k]) for k in ("demand_s", "warmup_s") if float(row.get(k) or 0)}
        return {**values, "inflow_vph": inflow, **timing}
    try:
        return {**values, "n_vehicles": int(row["n_vehicles"])}
    except ValueError:
        raise EvaluationError(
            f"{source}: field 'n_vehicles' is not a whole number ({row['n_vehicles']!r}); "
            "the file is damaged"
        ) from None
