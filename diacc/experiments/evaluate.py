"""Evaluation runner: every grid cell x K seeded episodes, in worker processes.

A results directory holds one policy on one backend::

    results/<dir>/meta.json                 what was evaluated (policy, backend, settings)
    results/<dir>/cells/<cell>.episodes.csv one row per episode of a finished cell
    results/<dir>/cells/<cell>.speeds.csv.gz per-vehicle speed samples of that cell
    results/<dir>/episodes.csv              all finished cells, merged (tidy, one row per episode)
    results/<dir>/speeds.csv.gz             all speed samples, merged
    results/<dir>/eval.log                  recoveries: restarted workers, damaged cells

A cell's files are written (atomically) only once all its K episodes are in,
so an interrupted run loses at most the cells in flight, and re-running the
same command skips every finished cell. Results kept as the merged files only
(committed results leave ``cells/`` and the speed samples out) count too: a run
over them keeps their rows in ``cells/merged-only.csv``, skips their cells and
merges them with the cells it adds. Episode seeds depend on the cell and
the episode number only (:meth:`diacc.experiments.grid.Cell.seed`), so every policy meets
exactly the same traffic draws and results do not depend on ``--workers``.

Faults: a cell whose files are damaged (truncated, edited) is reported and
recomputed; a dead pool worker costs a retry of its task
(:mod:`diacc.experiments.workpool`); a dead simulator a retry of its episode
(:func:`run_cell_task`). Each recovery is logged, so results are complete
and equal to an unfaulted run's, or the command ends with a one-line error.

Episodes are played by :class:`diacc.envs.episode.EpisodeDriver`, so they end
like training episodes: on a collision, when every vehicle has left, or
after ``episode_steps``.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from diacc.envs.actions import ACTION_NAMES
from diacc.envs.episode import EpisodeDriver, play_episode
from diacc.envs.psar import RULE_NAMES
from diacc.experiments.grid import Cell
from diacc.experiments.policies import CheckpointPolicy, EvalSettings, PolicySpec, build_policy
from diacc.experiments.results_files import (
    CELLS_DIR,
    EPISODES_FILE,
    LOG_FILE,
    META_FILE,
    SPEED_COLUMNS,
    SPEEDS_FILE,
    EpisodeResult,
    EvaluationError,
    adopt_merged_only,
    cell_id,
    check_cell_files,
    csv_text,
    drop_if_damaged,
    load_episodes,
    merge_cells,
    merged_only_episodes,
    read_csv,
    write_cell,
)
from diacc.experiments.workpool import map_resilient
from diacc.fileio import atomic_write, check_output_dir, refuse_symlink
from diacc.learn.collapse import collapse_warning
from diacc.runlog import locked_dir, log, run_log
from diacc.sim.backends.base import BackendError
from diacc.sim.maps import SEGMENT_KINDS
from diacc.threads import default_threads, worker_environment
from diacc.tomlfile import read_json_object

#: Attempts per episode when its simulator dies (the first run plus retries).
SIM_ATTEMPTS = 3
#: Names of :mod:`diacc.experiments.results_files` that callers import from here.
__all__ = [
    "CELLS_DIR",
    "EPISODES_FILE",
    "LOG_FILE",
    "META_FILE",
    "SPEED_COLUMNS",
    "SPEEDS_FILE",
    "EpisodeResult",
    "EvaluationError",
    "check_cell_files",
    "csv_text",
    "load_episodes",
    "read_csv",
]

#: Most worker processes of one evaluation: each holds a simulator and torch (about
#: 0.4 GB, docs/guide/faults.md), so 64 fill a 24 GiB machine.
MAX_WORKERS = 64
#: Most episodes per cell (the paper runs 10): the cell's episode list and results are
#: held in memory, and each episode is seconds of simulation.
MAX_EPISODES = 10_000


# ----------------------------------------------------------------------------- one episode
def run_episode(driver: EpisodeDriver, cell: Cell, episode: int, stream: str) -> EpisodeResult:
    """Play one seeded episode of a seed stream to its end and summarise it."""
    seed = cell.seed(episode, stream)
    recorder = play_episode(driver, seed)
    metrics = recorder.summary()
    speeds = recorder.speed_samples()
    row = {
        "policy": driver.policy.label,
        "backend": driver.cfg.backend,
        "sumo_version": driver.backend.version,
        "style_preset": driver.cfg.sim.style_preset,
        **cell.as_row(),
        "inflow_vph": cell.inflow_vph,
        "demand_s": cell.demand_s,  # a demand cell's timing (0: the defaults)
        "warmup_s": cell.warmup_s,
        "stream": stream,
        "episode": episode,
        "seed": seed,
        "n_cavs": driver.cfg.scenario.n_cavs,
        "psar": driver.cfg.psar_enabled,
        "steps": driver.steps,
        "collision": int(driver.env.batch.state.wrecked.any()),  # anywhere, warm-up too
        "mean_speed_mps": metrics.mean_speed_mps,
        "std_speed_mps": metrics.std_speed_mps,
        "n_speed_samples": int(speeds.speed_mps.shape[0]),
        "mean_cav_speed_mps": metrics.mean_cav_speed_mps,
        "mean_hdv_speed_mps": metrics.mean_hdv_speed_mps,
        **{f"speed_{kind}_mps": metrics.mean_speed_by_kind_mps[kind] for kind in SEGMENT_KINDS},
        "p_we": metrics.p_we,
        "p_sce": metrics.p_sce,
        "n_collisions": metrics.n_collisions,
        "n_hdv_collisions": metrics.n_hdv_collisions,
        "arrived_fraction": metrics.arrived_fraction,
        "mean_travel_time_s": metrics.mean_travel_time_s,
        "n_vehicles_seen": metrics.n_vehicles,
        "throughput_vph": metrics.throughput_vph,
        "total_delay_s": metrics.total_delay_s,
        "delay_per_vehicle_s": metrics.delay_per_vehicle_s,
        "mean_arrived_speed_mps": metrics.mean_arrived_speed_mps,
        "never_arrived_fraction": metrics.never_arrived_fraction,
        "psar_decisions": metrics.psar_decisions,
        **{f"psar_{name}_rate": metrics.psar_fire_rate[name] for name in RULE_NAMES[1:]},
    }
    return EpisodeResult(cell, episode, row, speeds, driver.picked.copy())


# ----------------------------------------------------------------------------- workers
_WORKER: dict = {}


def _init_worker(spec: PolicySpec, settings: EvalSettings, threads: int = 1) -> None:
    """Per-process state: the policy and the driver of the last cell (one SUMO at a time)."""
    try:
        import torch

        torch.set_num_threads(threads)
    except ImportError:  # pragma: no cover - torch is a dependency
        pass
    _close_worker_driver()
    _WORKER.update(policy=build_policy(spec), settings=settings, key=None, driver=None)


def _close_worker_driver() -> None:
    if _WORKER.get("driver") is not None:
        _WORKER["driver"].close()
    _WORKER.update(driver=None, key=None)


@dataclass(frozen=True)
class CellTask:
    """A unit of evaluation work: some episodes of one cell (what a worker runs in one go)."""

    cell: Cell
    episodes: tuple[int, ...]


@dataclass
class CellTaskResult:
    task: CellTask
    results: list[EpisodeResult]
    notes: list[str]  # recoveries inside the worker (simulator restarts), for the run log


def _driver(cell: Cell) -> EpisodeDriver:
    if _WORKER["key"] != cell.key:
        _close_worker_driver()
        cfg = _WORKER["policy"].env_config(cell, _WORKER["settings"])
        _WORKER.update(driver=EpisodeDriver(_WORKER["policy"], cfg), key=cell.key)
    return _WORKER["driver"]


def run_cell_task(task: CellTask) -> CellTaskResult:
    """Run a task's episodes in this (initialised) process.

    A simulator that dies (:class:`BackendError`: SUMO worker killed or
    crashed) costs only its episode, which is re-run from its seed on a fresh
    simulator, at most :data:`SIM_ATTEMPTS` times in all; seeds fix the
    traffic, so a retried episode is the episode an unfaulted run plays.
    """
    results, notes = [], []
    with _captured(notes):
        for episode in task.episodes:
            for attempt in range(1, SIM_ATTEMPTS + 1):
                try:
                    driver = _driver(task.cell)
                    stream = _WORKER["settings"].stream
                    results.append(run_episode(driver, task.cell, episode, stream))
                    break
                except BackendError as exc:
                    _close_worker_driver()
                    if attempt == SIM_ATTEMPTS:
                        raise BackendError(
                            f"cell {task.cell.key} episode {episode} failed {attempt} times: {exc}"
                        ) from None
                    notes.append(
                        f"cell {task.cell.key} episode {episode}: {str(exc).splitlines()[0]}; "
                        f"re-running it on a new simulator "
                        f"(attempt {attempt + 1} of {SIM_ATTEMPTS})"
                    )
    return CellTaskResult(task, results, notes)


@contextmanager
def _captured(notes: list[str]) -> Iterator[None]:
    """In a pool worker, collect diacc's log records into ``notes`` (the parent logs them)."""
    if not _WORKER.get("capture"):
        yield
        return
    handler = _ListHandler(notes)
    log.addHandler(handler)
    log.propagate = False
    try:
        yield
    finally:
        log.removeHandler(handler)
        log.propagate = True


class _ListHandler(logging.Handler):
    def __init__(self, notes: list[str]) -> None:
        super().__init__(logging.WARNING)
        self.notes = notes

    def emit(self, record: logging.LogRecord) -> None:
        self.notes.append(record.getMessage())


def _init_pool_worker(spec: PolicySpec, settings: EvalSettings) -> None:
    _init_worker(spec, settings)
    _WORKER["capture"] = True


def cell_tasks(cells: list[Cell], episodes: int, workers: int) -> list[CellTask]:
    """Split each cell's episodes into tasks: about 4 tasks per worker keeps workers busy."""
    chunk = max(1, min(episodes, math.ceil(len(cells) * episodes / (4 * workers))))
    return [
        CellTask(cell, tuple(range(start, min(start + chunk, episodes))))
        for cell in cells
        for start in range(0, episodes, chunk)
    ]


def run_tasks_here(
    tasks: list[CellTask], spec: PolicySpec, settings: EvalSettings, threads: int = 1
) -> Iterator[CellTaskResult]:
    """Run tasks one after another in this process (also what one Ray task does)."""
    _init_worker(spec, settings, threads=threads)
    try:
        yield from map(run_cell_task, tasks)
    finally:
        _close_worker_driver()


def run_local(
    tasks: list[CellTask], spec: PolicySpec, settings: EvalSettings, workers: int
) -> Iterator[CellTaskResult]:
    """The default evaluation engine: this process (``workers`` = 1) or a resilient pool.

    Any engine takes the same arguments and yields one :class:`CellTaskResult`
    per task, in any order (see :func:`evaluate`'s ``engine``).
    """
    if workers <= 1:
        yield from run_tasks_here(tasks, spec, settings, threads=default_threads())
        return
    # The pool (re)starts workers at any time: they inherit one library thread (diacc.threads).
    with worker_environment():
        for _, result in map_resilient(
            run_cell_task,
            tasks,
            workers,
            initializer=_init_pool_worker,
            initargs=(spec, settings),
            describe=lambda t: f"cell {t.cell.key} episodes {t.episodes[0]}-{t.episodes[-1]}",
        ):
            yield result


#: An evaluation engine: (tasks, policy, settings, workers) -> one result per task, any order.
Engine = Callable[[list[CellTask], PolicySpec, EvalSettings, int], Iterator[CellTaskResult]]


def _psar_before_recorded(policy) -> dict:
    """PSAR settings a policy ran with, unasked, before ``meta.json`` recorded them.

    A checkpoint keeps the settings of its stored config; every other policy
    took :class:`~diacc.config.PSARConfig`'s defaults of the time: horizon
    ``"stopping"`` until it became ``"headway"``, ``full_brake`` ``"bound"`` until it
    became ``"threat"`` (both changed together; docs/concepts/psar.md).
    """
    if isinstance(policy, CheckpointPolicy):
        psar = policy.base.psar
        return {"psar_horizon": psar.horizon, "psar_full_brake": psar.full_brake}
    return {"psar_horizon": "stopping", "psar_full_brake": "bound"}


def evaluation_meta(policy, cells: list[Cell], settings: EvalSettings) -> tuple[dict, dict | None]:
    """What ``meta.json`` records of an evaluation, and how to read an older one.

    The agent slots are recorded where they matter, for demand cells, and there unless
    ``own`` (a ``meta.json`` without them ran with the policy's own). Returns ``(meta,
    before)``: the policy, backend and settings, the settings with the PSAR horizon and
    ``full_brake`` in effect (asked for or not, so that no run adds episodes of another
    PSAR to a results directory: the defaults changed, the directory may be older);
    ``before`` holds the values a ``meta.json`` that does not name them ran with (None:
    the policy runs without PSAR).
    """
    meta = {**policy.describe(), **settings.describe()}
    if not any(cell.scenario(base=policy.base.scenario).kind == "demand" for cell in cells):
        # a release slots every CAV whatever the setting: older results stay reusable
        meta["settings"].pop("agent_slots", None)
    env = policy.env_config(cells[0], settings)  # every cell shares PSAR and simulation
    before = {"on_collision": "end"}  # every episode ended at a collision before it was named
    if not env.psar_enabled:
        return meta, before
    in_effect = {"psar_horizon": env.psar.horizon, "psar_full_brake": env.psar.full_brake}
    meta["settings"] = {**meta["settings"], **in_effect}
    return meta, {**before, **_psar_before_recorded(policy)}


def meta_conflict(old: dict, meta: dict, before: dict | None) -> str | None:
    """The first key in which an existing ``meta.json`` differs from ``meta``, else None."""
    if isinstance(old.get("settings"), dict):  # a meta.json before streams ran on legacy seeds
        old = {**old, "settings": {"stream": "legacy", **(before or {}), **old["settings"]}}
    for key in ("policy", "checkpoint", "backend", "settings"):
        if old.get(key) != meta.get(key):
            return key
    return None


def _which_setting(old: dict, meta: dict) -> str:
    """`` (stream: legacy, asked test)`` for the first setting that differs, else ""."""
    mine, theirs = meta.get("settings", {}), old.get("settings")
    if not isinstance(theirs, dict):
        return ""
    theirs = {"stream": "legacy", **theirs}  # a meta.json before streams ran on legacy seeds
    for name, value in mine.items():
        if name in theirs and theirs[name] != value:
            return f" ({name}: {theirs[name]}, asked {value})"
    return ""


def _check_meta(out_dir: Path, meta: dict, before: dict | None = None) -> None:
    """Refuse a results directory that holds another evaluation; write ``meta.json``."""
    path = out_dir / META_FILE
    if path.exists():
        old = read_json_object(path, EvaluationError)
        key = meta_conflict(old, meta, before)
        if key is not None:
            raise EvaluationError(
                f"results directory {out_dir} holds {old.get('policy')} on "
                f"{old.get('backend')} with other {key!r}{_which_setting(old, meta)}; "
                "choose another --out"
            )
    out_dir.mkdir(parents=True, exist_ok=True)
    atomic_write(path, json.dumps(meta, indent=2).encode())


@dataclass
class EvalSummary:
    out_dir: Path
    cells_run: list[Cell]
    cells_skipped: list[Cell]


def evaluate(
    spec: PolicySpec,
    cells: list[Cell],
    episodes: int,
    out_dir: str | Path,
    settings: EvalSettings,
    workers: int = 1,
    progress: bool = True,
    engine: Engine | None = None,
    on_cell: Callable[[Cell, list[EpisodeResult]], None] | None = None,
) -> EvalSummary:
    """Evaluate a policy on every cell for ``episodes`` seeded episodes (see module docstring).

    ``engine`` runs the cell tasks (default :func:`run_local`; or
    :class:`diacc.experiments.scaleout.RayEngine`, one Ray task per cell); recoveries it
    reports, and damaged cell files found here, are logged to stderr and to
    ``<out_dir>/eval.log``. ``on_cell`` is called with each cell and its
    episodes once its files are written (``diacc reproduce`` prints a line).
    """
    out_dir = Path(out_dir)
    if not 1 <= episodes <= MAX_EPISODES:
        raise EvaluationError(
            f"--episodes must be in [1, {MAX_EPISODES}], got {episodes} (per cell; each is "
            "seconds of simulation and a results row, all held in memory)"
        )
    if not 1 <= workers <= MAX_WORKERS:
        raise EvaluationError(
            f"--workers must be in [1, {MAX_WORKERS}], got {workers} (each is a process "
            "with its own simulator and torch, about 0.4 GB)"
        )
    if not cells:
        raise EvaluationError("the grid has no cells")
    policy = build_policy(spec)  # fail fast on a bad checkpoint, in this process
    for cell in cells:
        policy.env_config(cell, settings)  # fail fast on cells the policy cannot run
    meta, before = evaluation_meta(policy, cells, settings)
    with locked_dir(out_dir, "eval"):  # one writer; an unusable --out is one line
        for name in (META_FILE, EPISODES_FILE, SPEEDS_FILE, CELLS_DIR, LOG_FILE):
            refuse_symlink(out_dir / name)  # before anything is written
        check_output_dir(out_dir / CELLS_DIR)
        _check_meta(out_dir, meta, before)
        return _evaluate(
            spec, cells, episodes, out_dir, settings, workers, progress, engine, on_cell, policy
        )


def _evaluate(
    spec: PolicySpec,
    cells: list[Cell],
    episodes: int,
    out_dir: Path,
    settings: EvalSettings,
    workers: int,
    progress: bool,
    engine: Engine | None,
    on_cell: Callable[[Cell, list[EpisodeResult]], None] | None,
    policy,
) -> EvalSummary:
    """:func:`evaluate` once its inputs are checked and ``out_dir`` is locked."""
    with run_log(out_dir / LOG_FILE):
        adopt_merged_only(out_dir)  # committed results: merged files only
        merged = merged_only_episodes(out_dir)
        every = list(range(episodes))
        done = [
            drop_if_damaged(out_dir, c.file_key) == every
            or merged.get(cell_id({**c.as_row(), "inflow_vph": c.inflow_vph})) == every
            for c in cells
        ]
        todo = [c for c, d in zip(cells, done, strict=True) if not d]
        skipped = [c for c, d in zip(cells, done, strict=True) if d]
        pending: dict[str, list[EpisodeResult]] = {c.key: [] for c in todo}
        from tqdm import tqdm

        bar = tqdm(
            total=len(todo) * episodes,
            unit="episode",
            disable=not progress or not todo,
            desc=f"eval {policy.label} on {settings.backend}",
        )
        tasks = cell_tasks(todo, episodes, workers)
        picked = np.zeros(len(ACTION_NAMES), np.int64)  # (A,) over this run's episodes
        try:
            for task_result in (engine or run_local)(tasks, spec, settings, workers):
                for note in task_result.notes:
                    log.warning(note)
                for result in task_result.results:
                    picked += result.picked
                    pending[result.cell.key].append(result)
                    if len(pending[result.cell.key]) == episodes:
                        finished = pending.pop(result.cell.key)
                        write_cell(out_dir, result.cell, finished)
                        if on_cell is not None:
                            on_cell(result.cell, finished)
                bar.update(len(task_result.results))
        finally:
            bar.close()
            merge_cells(out_dir)
        if isinstance(policy, CheckpointPolicy):  # scripted policies: one action by design
            collapsed = collapse_warning(f"checkpoint {policy.path}", picked)
            if collapsed is not None:
                log.warning(collapsed)  # on stderr and in eval.log
    return EvalSummary(out_dir, todo, skipped)
