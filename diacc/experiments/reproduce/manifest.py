"""``manifest.json`` of a reproduction: what was asked, with what software, what is done.

It records every invocation (command line, start and end time, exit), the
resolved configuration and budget, the package versions, and per stage
whether it finished and what it holds (runs and their steps, evaluation jobs,
output files and the fingerprint of their inputs). It is rewritten
atomically after every run and job, so a killed reproduction leaves a
manifest that says how far it got. Training and evaluation decide what to
skip from the files they produce, never from the manifest; the outputs are
rebuilt unless the manifest's fingerprint of their inputs still matches, so
a deleted manifest only costs a rebuild.
"""

from __future__ import annotations

import json
import platform
from dataclasses import asdict
from datetime import datetime, timezone
from importlib import metadata
from typing import Any

from diacc import __version__
from diacc.experiments.reproduce.plan import Plan
from diacc.fileio import atomic_write

MANIFEST_FILE = "manifest.json"
#: Distributions whose versions change results (simulators, learning stack).
VERSIONED = ("numpy", "torch", "highway-env", "eclipse-sumo", "libsumo", "ray")
STAGES = ("train", "eval", "outputs")


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def versions() -> dict[str, str]:
    """diacc, Python and the versions of :data:`VERSIONED` ("not installed" if absent)."""
    found = {"diacc": __version__, "python": platform.python_version()}
    for name in VERSIONED:
        try:
            found[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            found[name] = "not installed"
    return found


class Manifest:
    """The manifest file of one results directory; every change is saved at once."""

    def __init__(self, plan: Plan, argv: list[str]) -> None:
        self.path = plan.config.out_dir / MANIFEST_FILE
        old = self._read()
        invocations = old.get("invocations", [])
        invocations.append({"argv": argv, "started_utc": _now(), "finished_utc": None})
        self.data: dict[str, Any] = {
            "command": "diacc reproduce",
            "invocations": invocations,
            "config": asdict(plan.config),
            "versions": versions(),
            "seeds": list(plan.config.budget.seeds),
            "runs": {r.name: asdict(r) for r in plan.runs},
            "eval_jobs": {str(j.rel_dir): [c.key for c in j.cells] for j in plan.jobs},
            "stages": {s: {**old.get("stages", {}).get(s, {}), "finished": False} for s in STAGES},
        }
        self.save()

    def _read(self) -> dict:
        try:
            return json.loads(self.path.read_text())
        except (OSError, ValueError):
            return {}

    def stage(self, name: str, **info: Any) -> None:
        """Update a stage's entry (``finished=True`` marks it done)."""
        self.data["stages"][name].update(info)
        self.save()

    def finish(self, exit_status: str) -> None:
        self.data["invocations"][-1].update(finished_utc=_now(), exit=exit_status)
        self.save()

    def save(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(self.path, json.dumps(self.data, indent=2, default=str) + "\n")
