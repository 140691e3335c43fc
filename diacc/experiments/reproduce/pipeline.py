"""The three stages of ``diacc reproduce`` in order, with the manifest kept up to date.

1. training (:func:`diacc.experiments.reproduce.stages.train_all`),
2. evaluation (:func:`diacc.experiments.reproduce.stages.evaluate_all`),
3. outputs (:func:`diacc.experiments.reproduce.outputs.write_outputs`), skipped when
   their inputs have not changed since the last time they were written.

Each stage skips what is already done, so running the same command again
continues a killed reproduction, and re-running a finished one only checks.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from diacc.experiments.reproduce.manifest import MANIFEST_FILE, Manifest
from diacc.experiments.reproduce.outputs import inputs_fingerprint, write_outputs
from diacc.experiments.reproduce.plan import Execution, Plan
from diacc.experiments.reproduce.stages import (
    Say,
    check_existing_evaluations,
    check_existing_runs,
    evaluate_all,
    train_all,
)


@dataclass(frozen=True)
class Produced:
    """Where a reproduction's files are."""

    out_dir: Path
    outputs: tuple[Path, ...]  # tables, figures, transfer report
    outputs_rebuilt: bool

    def summary(self) -> list[str]:
        out = self.out_dir

        def under(folder: str) -> str:
            names = sorted(p.name for p in self.outputs if p.parent.name == folder)
            return ", ".join(names)

        lines = [
            f"results in {out}:",
            "  runs/       training runs (checkpoint.pt, progress.jsonl, tb/)",
            "  eval/       evaluation results per backend and policy (episodes.csv, speeds.csv.gz)",
            f"  tables/     {under('tables')}",
            f"  figures/    {under('figures')}",
        ]
        if any(p.name == "transfer.md" for p in self.outputs):
            lines.append("  transfer.md, transfer.csv   sim-to-sim transfer")
        lines.append(f"  {MANIFEST_FILE}   invocations, versions, plan, finished stages")
        if not self.outputs_rebuilt:
            lines.append("  (outputs were up to date: their inputs had not changed)")
        return lines


def reproduce(plan: Plan, execution: Execution, argv: list[str], say: Say = print) -> Produced:
    """Run (or continue) a reproduction; returns where its outputs are."""
    check_existing_runs(plan)
    check_existing_evaluations(plan)
    manifest = Manifest(plan, argv)
    status = "interrupted"
    try:
        say(f"stage 1/3: training, {len(plan.runs)} runs")
        steps: dict[str, int] = {}

        def on_run(run) -> None:
            steps[Path(run.run_dir).name] = int(run.last.get("global_step", 0))
            manifest.stage("train", env_steps=steps)

        trained = train_all(plan, execution, say, on_run)
        manifest.stage("train", finished=True)
        say(f"stage 2/3: evaluation, {len(plan.jobs)} (policy, backend) jobs")
        done: list[str] = []

        def on_job(job) -> None:
            done.append(str(job.rel_dir))
            manifest.stage("eval", jobs_done=done)

        evaluate_all(plan, execution, trained, say, on_job)
        manifest.stage("eval", finished=True)
        say("stage 3/3: tables, figures" + (", transfer report" if plan.transfer_pairs else ""))
        fingerprint = inputs_fingerprint(plan)
        old = manifest.data["stages"]["outputs"]
        files = [plan.config.out_dir / f for f in old.get("files", [])]
        up_to_date = old.get("fingerprint") == fingerprint and files
        rebuilt = not (up_to_date and all(path.exists() for path in files))
        if rebuilt:
            files = write_outputs(plan)
        manifest.stage(
            "outputs",
            finished=True,
            fingerprint=fingerprint,
            files=[str(p.relative_to(plan.config.out_dir)) for p in files],
        )
        status = "finished"
    except Exception as exc:
        status = f"failed: {type(exc).__name__}"
        raise
    finally:
        manifest.finish(status)
    return Produced(plan.config.out_dir, tuple(files), rebuilt)
