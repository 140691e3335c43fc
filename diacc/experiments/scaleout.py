"""Scale-out with Ray: evaluation grids and training sweeps as Ray tasks.

Ray is optional (``pip install -e ".[ray]"``); without it the local engines
(worker processes for ``diacc eval``, one run after the other for ``diacc
sweep``) do the same work on one machine. With ``--engine ray``:

* ``diacc eval``: every grid cell is one Ray task that plays the cell's K
  seeded episodes (:func:`diacc.experiments.evaluate.run_tasks_here`) and sends the
  results back; the driver writes the files, so results need no shared filesystem.
  Seeds depend on (cell, episode) only, so the files are identical to a local run's.
* ``diacc sweep``: every (variant, map, setting, seed) run is one Ray task that calls
  the trainer. Run directories are written where the task runs: on a cluster,
  put ``--out`` on a filesystem all machines share (NFS), or collect the
  directories from the machines each run reports.

Ray runs on a local instance started for the command (``--ray-cpus`` CPUs)
unless ``--ray-address`` names a running cluster (``auto``, ``HOST:6379``, or
``ray://HOST:10001``). Every machine of the cluster needs the same diacc
installed (see docs/guide/scaling-out.md).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import signal
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from diacc.config import ConfigError, TrainConfig, override
from diacc.errors import DiaccError
from diacc.experiments.evaluate import CellTask, CellTaskResult, run_tasks_here
from diacc.experiments.grid import Cell
from diacc.experiments.policies import EvalSettings, PolicySpec
from diacc.experiments.sweepaxes import Setting
from diacc.sim.maps import map_tag
from diacc.tomlfile import read_json_object

ENGINES = ("local", "ray")
RAY_MISSING = 'Ray is not installed: pip install -e ".[ray]" (or use --engine local)'


class ScaleoutError(DiaccError, RuntimeError):
    """Ray missing, unreachable or failing; the message is one line."""


# ----------------------------------------------------------------------------- Ray session
def _ray():
    try:
        import ray
    except ImportError:
        raise ScaleoutError(RAY_MISSING) from None
    return ray


def connect(address: str | None = None, num_cpus: int | None = None):
    """The ``ray`` module, connected: to ``address``'s cluster, else to a new local instance.

    An already initialised Ray session (a test's, a notebook's) is reused as is.
    """
    ray = _ray()
    if ray.is_initialized():
        return ray
    options: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
    sigterm = signal.getsignal(signal.SIGTERM)
    try:
        if address:
            ray.init(address=address, **options)
        else:
            ray.init(num_cpus=num_cpus, **options)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        where = f"the Ray cluster at {address}" if address else "a local Ray instance"
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ScaleoutError(f"could not start or reach {where}: {first}") from None
    finally:
        # ray.init replaces the SIGTERM handler with one that exits with status 1;
        # the caller's (the CLI's: an exception, so exit 143 after cleanup) comes back.
        # Ray's own atexit hook then stops the local instance (raylet, GCS, workers).
        if sigterm is not None and threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGTERM, sigterm)
    return ray


def _unwrap(exc: BaseException) -> BaseException:
    """The user-facing exception inside a Ray task error (one-line message)."""
    cause = getattr(exc, "cause", None)
    return cause if isinstance(cause, Exception) else exc


def _as_completed(ray, refs: list) -> Iterator[Any]:
    """Results of Ray tasks in the order they finish; a failed task raises its own error."""
    pending = list(refs)
    while pending:
        done, pending = ray.wait(pending, num_returns=1)
        try:
            yield ray.get(done[0])
        except ray.exceptions.RayError as exc:
            for ref in pending:
                ray.cancel(ref)
            raise _unwrap(exc) from None


def _limit_threads(cpus: float) -> None:
    """Keep torch to the CPUs Ray gave the task (no oversubscription)."""
    import torch

    torch.set_num_threads(max(1, int(cpus)))


# ----------------------------------------------------------------------------- evaluation
def _run_cell(spec: PolicySpec, settings: EvalSettings, tasks: list[CellTask]):
    """One Ray task: every task of one cell, in this process (one SUMO per cell)."""
    _limit_threads(1)
    return list(run_tasks_here(tasks, spec, settings, threads=1))


@dataclass(frozen=True)
class RayEngine:
    """Evaluation engine for :func:`diacc.experiments.evaluate.evaluate`: one Ray task per
    grid cell."""

    address: str | None = None
    num_cpus: int | None = None  # of the local instance (all CPUs if None)

    def __call__(
        self, tasks: list[CellTask], spec: PolicySpec, settings: EvalSettings, workers: int
    ) -> Iterator[CellTaskResult]:
        ray = connect(self.address, self.num_cpus)
        by_cell: dict[Cell, list[CellTask]] = {}
        for task in tasks:
            by_cell.setdefault(task.cell, []).append(task)
        remote = ray.remote(num_cpus=1)(_run_cell)
        refs = [remote.remote(spec, settings, cell_tasks) for cell_tasks in by_cell.values()]
        for results in _as_completed(ray, refs):
            yield from results


# ----------------------------------------------------------------------------- sweeps
@dataclass(frozen=True)
class SweepRun:
    """One run of a sweep and where it went."""

    variant: str
    map: str
    seed: int
    run_dir: str
    status: str  # "trained", "resumed", "skipped" (already finished)
    host: str = ""
    wall_s: float = 0.0
    last: dict = dataclasses.field(default_factory=dict)  # last progress.jsonl record


def sweep_configs(
    base: TrainConfig,
    variants: list[str],
    maps: list[str],
    seeds: list[int],
    out_dir: str | Path,
    settings: list[Setting] | None = None,
) -> list[TrainConfig]:
    """The configs of variants x maps x settings x seeds, each with its own run directory.

    A setting's name ends the directory name
    (``<variant>-<backend>-<map>-s<seed>-tau_init2-tau_final0.05``), so runs
    that differ only in a setting never share a directory.
    """
    configs = []
    for variant, map_name, setting, seed in itertools.product(
        variants, maps, settings or [Setting()], seeds
    ):
        name = f"{variant}-{base.env.backend}-{map_tag(map_name)}-s{seed}"
        run_dir = Path(out_dir) / (f"{name}-{setting.name}" if setting.values else name)
        changes = {"variant": variant, "env.map": map_name, "seed": seed, "run_dir": str(run_dir)}
        configs.append(override(base, {**setting.changes, **changes}))
    return configs


def check_run_dirs(configs: list[TrainConfig]) -> None:
    """One-line :class:`ConfigError` if a run directory holds a run with other settings.

    Without it, a finished run trained with, say, another ``--set`` value
    would be skipped (its step count is reached) and reported as if it had
    this command's settings. Only the step budget may change (the run
    resumes). Fields added to the config after the run was trained count as
    their defaults, as when its checkpoint is evaluated.
    """
    for cfg in configs:
        path = Path(cfg.run_dir) / "config.json"
        changed = stored_config_changes(cfg)
        if changed:
            raise ConfigError(
                f"{path.parent} was trained with another {changed[0]} than this command asks "
                "for (see its config.json); repeat the options it was started with, or choose "
                "another output directory"
            )


def _last_record(run_dir: Path) -> dict:
    path = run_dir / "progress.jsonl"
    if not path.exists():
        return {}
    lines = [line for line in path.read_text(errors="replace").splitlines() if line.strip()]
    try:
        record = json.loads(lines[-1]) if lines else {}
    except (json.JSONDecodeError, RecursionError):
        return {}
    return record if isinstance(record, dict) else {}  # a damaged row: the run is not finished


def planned_steps(cfg: TrainConfig) -> int:
    """Environment steps a finished run has taken: whole updates, at least one."""
    per_update = cfg.rollout_steps * cfg.n_envs
    return max(1, cfg.total_steps // per_update) * per_update


def run_state(cfg: TrainConfig) -> str:
    """``finished`` (its last logged update reached the budget), ``checkpointed`` (it
    can resume) or ``new``: what :func:`train_run` will do with it."""
    run_dir = Path(cfg.run_dir)
    if _last_record(run_dir).get("global_step", 0) >= planned_steps(cfg):
        return "finished"
    return "checkpointed" if (run_dir / "checkpoint.pt").exists() else "new"


def stored_config_changes(cfg: TrainConfig) -> list[str]:
    """Fields (but the step budget) where ``cfg`` differs from its run directory's config.json.

    A run found finished is skipped and one found checkpointed is resumed:
    both only under the settings it was trained with, or the results would be
    reported under settings they were not made with. Fields added to the
    config after the run was trained count as their defaults (of that time:
    :func:`~diacc.learn.checkpoint.config_from_checkpoint`), so a run trained
    with the ``stopping`` horizon is not continued under today's ``headway``.
    """
    from diacc.learn.checkpoint import config_from_checkpoint
    from diacc.learn.trainer import check_resume_config

    path = Path(cfg.run_dir) / "config.json"
    if not path.exists():
        return []
    stored = read_json_object(path, ConfigError)
    try:
        saved = dataclasses.asdict(config_from_checkpoint({"config": stored}))
    except ValueError as exc:
        raise ConfigError(f"{path}: not a usable diacc config ({exc})") from None
    return check_resume_config(saved, cfg, path, allow_change=True)


def train_run(cfg: TrainConfig, progress: bool = False) -> SweepRun:
    """Train one sweep run: skipped if finished, resumed if it has a checkpoint.

    ``progress`` shows the trainer's progress bar (a run in the foreground).
    """
    from diacc.learn.mappo import train

    run_dir = Path(cfg.run_dir)
    base = {"variant": cfg.variant, "map": cfg.env.map, "seed": cfg.seed, "run_dir": cfg.run_dir}
    state = run_state(cfg)
    check_run_dirs([cfg])  # also here: a Ray task may find a run another command started
    if state == "finished":
        return SweepRun(
            **base, status="skipped", host=socket.gethostname(), last=_last_record(run_dir)
        )
    start = time.perf_counter()
    # A "new" run may hold the files of one killed before its first checkpoint, with
    # this very config (checked above): nothing to keep, so it starts again.
    train(cfg, resume=state == "checkpointed", overwrite=state == "new", progress=progress)
    return SweepRun(
        **base,
        status="resumed" if state == "checkpointed" else "trained",
        host=socket.gethostname(),
        wall_s=time.perf_counter() - start,
        last=_last_record(run_dir),
    )


def _train_run_task(cfg: TrainConfig, cpus: float) -> SweepRun:
    _limit_threads(cpus)
    return train_run(cfg)


def run_sweep(
    configs: list[TrainConfig],
    engine: str = "local",
    address: str | None = None,
    num_cpus: int | None = None,
    cpus_per_run: float = 1.0,
) -> Iterator[SweepRun]:
    """Train every config, one after the other (local) or as parallel Ray tasks (ray)."""
    if engine not in ENGINES:
        raise ScaleoutError(f"unknown engine {engine!r}; use one of {', '.join(ENGINES)}")
    if not configs:
        raise ScaleoutError("the sweep has no runs")
    if cpus_per_run <= 0:
        raise ScaleoutError(f"--cpus-per-run must be > 0, got {cpus_per_run}")
    if engine == "local":
        for cfg in configs:
            yield train_run(cfg)
        return
    ray = connect(address, num_cpus)
    remote = ray.remote(num_cpus=cpus_per_run)(_train_run_task)
    yield from _as_completed(ray, [remote.remote(cfg, cpus_per_run) for cfg in configs])
