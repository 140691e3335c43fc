"""Training and evaluation stages of ``diacc reproduce``, on the sweep and eval machinery.

* **Training**: every run of the plan through :func:`diacc.experiments.scaleout.train_run`
  (a finished run is skipped, an interrupted one resumed from its
  checkpoint): one after the other in this process (with the trainer's
  progress bar), in ``jobs`` worker processes (:func:`diacc.experiments.workpool.map_resilient`:
  a dead worker costs a retry, never a hang), or as Ray tasks
  (:func:`diacc.experiments.scaleout.run_sweep`).
* **Evaluation**: every (policy, backend) job through
  :func:`diacc.experiments.evaluate.evaluate`, which skips finished cells and recomputes
  damaged ones. A job whose cells are all intact is not even started (no
  checkpoint loading, no re-merge), so a finished reproduction re-runs in
  seconds. Results of a checkpoint that has since trained further are
  removed first: a results directory always describes the checkpoint as it is.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from diacc.config import ConfigError, TrainConfig
from diacc.console import plural
from diacc.experiments.evaluate import (
    EPISODES_FILE,
    META_FILE,
    SPEEDS_FILE,
    check_cell_files,
    evaluate,
    read_csv,
)
from diacc.experiments.grid import Cell
from diacc.experiments.policies import EvalSettings, PolicySpec, action_mode
from diacc.experiments.reproduce.plan import EvalJob, Execution, Plan
from diacc.experiments.scaleout import (
    SweepRun,
    check_run_dirs,
    planned_steps,
    run_state,
    run_sweep,
    train_run,
)
from diacc.experiments.workpool import map_resilient
from diacc.threads import worker_environment
from diacc.tomlfile import read_json_object

#: Where a stage's one-line progress messages go (``print`` in the CLI).
Say = Callable[[str], None]


# ----------------------------------------------------------------------------- training
def _train_local(configs: list[TrainConfig], progress: bool, say: Say) -> Iterator[SweepRun]:
    """One run after the other in this process; a line before each run that has work."""
    for k, cfg in enumerate(configs, 1):
        state = run_state(cfg)
        if state != "finished":
            how = "resuming from its checkpoint" if state == "checkpointed" else "starting"
            say(f"[{k}/{len(configs)}] train {Path(cfg.run_dir).name}: {how}")
        yield train_run(cfg, progress)


def _train_pool(configs: list[TrainConfig], jobs: int) -> Iterator[SweepRun]:
    # Pool workers start with one library thread each (diacc.threads); each trainer
    # then applies its own torch thread rule (TrainConfig.torch_threads).
    with worker_environment():
        for _, run in map_resilient(
            train_run, configs, jobs, describe=lambda c: f"training run {Path(c.run_dir).name}"
        ):
            yield run


def check_existing_runs(plan: Plan) -> None:
    """One-line :class:`ConfigError` if a run directory holds a run with other settings
    (:func:`diacc.experiments.scaleout.check_run_dirs`)."""
    check_run_dirs([plan.train_config(run) for run in plan.runs])


def check_existing_evaluations(plan: Plan) -> None:
    """One-line :class:`ConfigError` if an evaluation directory holds other settings.

    The counterpart of :func:`check_existing_runs` for what only evaluation
    reads (``--episode-steps``, ``--actions``): a complete job is skipped
    without running :func:`~diacc.experiments.evaluate.evaluate`, whose own check would
    never see the change, so the tables would report greedy results as
    sampled ones.
    """
    from diacc.experiments.evaluate import META_FILE, evaluation_meta, meta_conflict
    from diacc.experiments.policies import build_policy

    for job in plan.jobs:
        path = plan.eval_dir(job) / META_FILE
        if not path.exists():
            continue
        meta = read_json_object(path, ConfigError)
        spec = job_spec(plan, job)
        wanted, before = evaluation_meta(
            build_policy(spec), list(job.cells), job_settings(plan, job)
        )
        # Actions first: they also change a checkpoint's policy label.
        key = None
        if job.run is not None and meta.get("actions") != action_mode(spec.sampled):
            key = "actions"
        key = key or meta_conflict(meta, wanted, before)
        if key is not None:
            raise ConfigError(
                f"{path.parent} holds evaluations with another {key} ({meta.get(key)!r}, "
                f"this command asks for {wanted.get(key)!r}); repeat the options it was started "
                "with, or choose another --out"
            )


def train_all(
    plan: Plan, execution: Execution, say: Say, on_run: Callable[[SweepRun], None]
) -> dict[str, int]:
    """Train (or skip, or resume) every run; returns run name -> environment steps trained."""
    configs = [plan.train_config(run) for run in plan.runs]
    if execution.engine == "ray":
        results = run_sweep(
            configs, "ray", execution.ray_address, execution.ray_cpus, execution.cpus_per_run
        )
    elif execution.jobs > 1:
        results = _train_pool(configs, execution.jobs)
    else:
        results = _train_local(configs, execution.progress, say)
    planned = {Path(cfg.run_dir).name: planned_steps(cfg) for cfg in configs}
    trained = {}
    for k, run in enumerate(results, 1):
        name = Path(run.run_dir).name
        trained[name] = int(run.last.get("global_step", 0))
        took = f" in {run.wall_s:.1f} s" if run.wall_s else ""
        where = f" on {run.host}" if execution.engine == "ray" and run.host else ""
        more = (
            f" (more than the {planned[name]:,} planned: an earlier --steps was larger)"
            if trained[name] > planned[name]
            else ""
        )
        say(
            f"[{k}/{len(configs)}] {run.status} {name}{where}{took}: "
            f"{trained[name]:,} env steps{more}"
        )
        on_run(run)
    return trained


# ----------------------------------------------------------------------------- evaluation
def row_cell_key(row: dict[str, str]) -> str:
    """The cell key of an ``episodes.csv`` row."""
    cell = Cell(row["map"], int(row["n_vehicles"]), float(row["cav_penetration"]), row["style_mix"])
    return cell.key


def is_complete(out_dir: Path, cells: tuple[Cell, ...], episodes: int) -> bool:
    """Whether every cell is intact with exactly ``episodes`` episodes and merged.

    :func:`diacc.experiments.evaluate.merge_cells` writes the merged episodes file, then
    the merged speeds file: a speeds file older than the episodes file (or
    none) means a merge was cut short, and the job is handed to ``evaluate``,
    which merges again. (A copy that reorders modification times only costs
    that re-merge.)
    """
    merged, speeds = out_dir / EPISODES_FILE, out_dir / SPEEDS_FILE
    if not merged.exists() or not speeds.exists() or not (out_dir / META_FILE).exists():
        return False
    if speeds.stat().st_mtime_ns < merged.stat().st_mtime_ns:
        return False
    if any(check_cell_files(out_dir, c.file_key) != (list(range(episodes)), None) for c in cells):
        return False
    have = {(row_cell_key(r), int(r["episode"])) for r in read_csv(merged)}
    return all((c.key, e) in have for c in cells for e in range(episodes))


def _drop_stale(out_dir: Path, trained_steps: int, say: Say) -> None:
    """Remove the results of a checkpoint that has trained further since."""
    meta_path = out_dir / META_FILE
    if not meta_path.exists():
        return
    try:
        evaluated = read_json_object(meta_path, ConfigError).get("trained_steps")
    except ConfigError:  # damaged: the results are recomputed like stale ones
        evaluated = None
    if evaluated != trained_steps:
        say(
            f"  {out_dir}: results of the checkpoint at {evaluated} steps removed; "
            f"it has {trained_steps} now"
        )
        shutil.rmtree(out_dir)


def _cell_reporter(tag: str, n_cells: int, say: Say) -> Callable[[Cell, list], None]:
    """The line printed when an evaluation cell is finished: its mean speed, as in the tables."""
    count = iter(range(1, n_cells + 1))

    def report(cell: Cell, results: list) -> None:
        samples = sum(r.row["n_speed_samples"] for r in results)
        speed = sum(r.row["mean_speed_mps"] * r.row["n_speed_samples"] for r in results)
        say(
            f"  {tag} cell [{next(count)}/{n_cells}] {cell.key}: mean speed "
            f"{speed / max(samples, 1):.2f} m/s over {plural(len(results), 'episode')}"
        )

    return report


def job_spec(plan: Plan, job: EvalJob) -> PolicySpec:
    """The policy an evaluation job runs (checkpoints checked against their variant)."""
    if job.run is None:
        return PolicySpec(job.policy)
    return PolicySpec(
        str(plan.run_dir(job.run) / "checkpoint.pt"),
        job.run.variant,
        sampled=plan.config.actions == "sampled",
    )


def job_settings(plan: Plan, job: EvalJob) -> EvalSettings:
    """The evaluation settings of a job: its backend, the command's episode length, preset
    and seed stream."""
    cfg = plan.config
    return EvalSettings(
        backend=job.backend,
        episode_steps=cfg.episode_steps,
        style_preset=cfg.style_preset,
        stream=cfg.stream,
    )


@dataclass(frozen=True)
class _JobTask:
    """One evaluation job as a picklable task (what a pool worker runs)."""

    plan: Plan
    job: EvalJob
    tag: str  # "[k/n]", printed with its cells
    workers: int  # evaluation workers of this job (1 inside a job-level pool)
    progress: bool
    engine: Any = None  # RayEngine or None (local)


def _say(line: str) -> None:
    print(line, flush=True)


def _unfinished(plan: Plan, job: EvalJob) -> list[Cell]:
    episodes = list(range(plan.config.budget.episodes_per_cell))
    return [c for c in job.cells if check_cell_files(plan.eval_dir(job), c.file_key)[0] != episodes]


def run_job(task: _JobTask, say: Say = _say) -> int:
    """Evaluate one job's unfinished cells (a line per cell); returns how many it ran."""
    plan, job = task.plan, task.job
    summary = evaluate(
        job_spec(plan, job),
        list(job.cells),
        plan.config.budget.episodes_per_cell,
        plan.eval_dir(job),
        job_settings(plan, job),
        workers=task.workers,
        progress=task.progress,
        engine=task.engine,
        on_cell=_cell_reporter(task.tag, len(_unfinished(plan, job)), say),
    )
    return len(summary.cells_run)


def evaluate_all(
    plan: Plan,
    execution: Execution,
    trained: dict[str, int],
    say: Say,
    on_job: Callable[[EvalJob], None],
) -> None:
    """Run every evaluation job of the plan that is not complete yet.

    Locally with ``jobs`` > 1, whole jobs run in parallel worker processes
    (one pool for all of them: a pool per job would pay its start-up, about a
    torch import per worker, for every policy). One job at a time otherwise,
    its cells spread over Ray tasks with ``--engine ray``.
    """
    engine = None
    if execution.engine == "ray":
        from diacc.experiments.scaleout import RayEngine

        engine = RayEngine(execution.ray_address, execution.ray_cpus)
    episodes = plan.config.budget.episodes_per_cell
    n = len(plan.jobs)
    pooled = execution.engine == "local" and execution.jobs > 1
    tasks = []
    for k, job in enumerate(plan.jobs, 1):
        out_dir = plan.eval_dir(job)
        label = f"[{k}/{n}] eval {job.policy} on {job.backend}"
        if job.run is not None:
            _drop_stale(out_dir, trained[job.run.name], say)
        if is_complete(out_dir, job.cells, episodes):
            say(f"{label}: all {len(job.cells)} cells already done")
            on_job(job)
            continue
        task = _JobTask(
            plan,
            job,
            f"[{k}/{n}]",
            workers=1,
            progress=execution.progress and not pooled,
            engine=engine,
        )
        if pooled:
            tasks.append(task)
            continue
        say(f"{label}: {len(_unfinished(plan, job))} of {len(job.cells)} cells to run")
        run_job(task, say)
        on_job(job)
    if not tasks:
        return
    with worker_environment():
        for i, ran in map_resilient(
            run_job,
            tasks,
            execution.jobs,
            describe=lambda t: f"evaluation of {t.job.policy} on {t.job.backend}",
        ):
            job = tasks[i].job
            say(
                f"{tasks[i].tag} eval {job.policy} on {job.backend}: done, {ran} of "
                f"{len(job.cells)} cells run"
            )
            on_job(job)
