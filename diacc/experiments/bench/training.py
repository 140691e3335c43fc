"""End-to-end training throughput: rollout + PPO update, env-steps per second.

Runs a few real updates of :func:`diacc.learn.mappo.train` per configuration,
in this process, one configuration after another in one run, and projects the
wall time of the paper's 3 M-step run from the measured rate. Rows:

* **learners**: ``paper learner`` (configs/paper-learner.toml: the paper's
  network sizes, 1 minibatch) and ``small learner`` (the defaults,
  configs/small-learner.toml: hidden 64, 4 minibatches), each alone, ``+ bf16``
  (``update_bf16``), ``+ overlap`` (``overlap``: the next rollout beside the
  update, on the second core) and
  both; ``+ compiled update`` (only where a C++ compiler or CUDA is present;
  the first update, which compiles, is not timed) and ``hidden 64 + concat
  TAIE heads`` (``model.taie_concat_heads``);
* **vector** (on the paper learner, as the recorded figures were measured):
  ``per-env envs``, the environments stepped one after another
  (``vector = "sync"``), next to ``thread policy``, where ``highway`` runs
  all envs on one batched simulator (:class:`diacc.envs.vector.BatchedVectorEnv`);
* **device** (``--only device``; first in every run whose ``--device`` is not
  the CPU): the learner on the CPU, then on ``--device`` with the eager
  update, the static update (``update_path``), the static update with the
  envs in one worker process per core, and compiled (:func:`device_rows`),
  each row with its learner seconds per update and env-steps/s;
* **threads** (paper learner too): torch's default intra-op threads (one per core) against
  :func:`diacc.threads.default_threads`, alone and **with a competing
  CPU-bound process** (a busy loop for their duration).

Every row also shows how the update's wall time splits, per core, into
rollout, learner and idle (:func:`core_shares`), and the table title the
machine's load average before and after: on a shared machine the absolute
rates move with the load, ratios within one run much less. A process with
two busy threads (``overlap``) also gets a larger share of a crowded
machine, so under load its wall-clock gain overstates what it gives on an
idle one; the CPU seconds per update and the rate they imply on an idle
2-core machine (rollout + learner in sequence, or the longer of the two
with ``overlap``; GIL contention between the threads not modelled) are
shown beside it.

The first update of every configuration pays start-up and is left out.
``--device cuda`` puts the learner on CUDA (rollouts stay on the CPU).

``diacc bench --training``; ``python -m diacc.experiments.bench.training --envs 16
--only learners``; ``--only demand`` for the demand scenario's row (4 envs x 600
steps, 3600 veh/h; minutes per update, so never part of the default run);
``--vector-only`` (= ``--only vector``) for the first two vector rows; ``--profile``
for :mod:`diacc.experiments.bench.update_profile`.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from rich.console import Console
from rich.table import Table

from diacc.config import PAPER_LEARNER, EnvConfig, TrainConfig, override
from diacc.errors import DiaccError
from diacc.learn.trainer import resolve_device, train

PAPER_STEPS = 3_000_000
#: The smaller networks of the learner-cost rows (the paper: hidden sizes "of the order 64-256").
SMALL_MODEL = {"model.hidden_dim": 64, "model.gru_hidden": 64}


def measure(
    variant: str,
    backend: str,
    n_envs: int,
    updates: int,
    device: str,
    rollout_steps: int = 100,
    vector: str = "auto",
    options: dict | None = None,
) -> dict:
    """Train ``updates`` updates; return env-steps/s of the whole loop and of rollouts.

    ``options`` are further config overrides (``torch_threads``, ``update_bf16``, ...);
    without any the learner is the default (small) one.
    """
    with tempfile.TemporaryDirectory() as tmp:
        cfg = override(
            TrainConfig(),
            {
                "variant": variant,
                "env.backend": backend,
                # episodes as long as a rollout at most: no rollout cuts an episode (config)
                "env.sim.episode_steps": min(rollout_steps, EnvConfig().sim.episode_steps),
                "n_envs": n_envs,
                "device": device,
                "rollout_steps": rollout_steps,
                "total_steps": updates * rollout_steps * n_envs,
                "run_dir": tmp,
                "checkpoint_every": 10_000,
                "vector": vector,
                **(options or {}),
            },
        )
        start = time.perf_counter()
        train(cfg, progress=False)
        seconds = time.perf_counter() - start
        records = [
            json.loads(line) for line in (Path(tmp) / "progress.jsonl").read_text().splitlines()
        ]
    # The first update pays for start-up (imports, worker spawn, compiling); report the rest.
    steady = records[1:] or records
    steps = rollout_steps * n_envs
    update_s = sum(1.0 / r["updates_per_s"] for r in steady) / len(steady)
    rollout_s = sum(steps / r["env_steps_per_s"] for r in steady) / len(steady)
    learn_s = sum(r["learner_s"] for r in steady) / len(steady)
    # CPU seconds per update barely move with the machine's load: the rate an idle
    # 2-core machine would reach follows from them (rollout then learner on one
    # core; with overlap side by side on two, the longer one setting the pace).
    rollout_cpu = sum(r["rollout_cpu_s"] for r in steady) / len(steady)
    learn_cpu = sum(r["learner_cpu_s"] for r in steady) / len(steady)
    overlap = bool((options or {}).get("overlap"))
    idle_update_s = max(rollout_cpu, learn_cpu) if overlap else rollout_cpu + learn_cpu
    return {
        "rollout_cpu_s": rollout_cpu,
        "learner_cpu_s": learn_cpu,
        "idle_steps_per_s": steps / idle_update_s,
        **core_shares(update_s, rollout_s, learn_s, bool((options or {}).get("overlap"))),
        "variant": variant,
        "backend": backend,
        "envs": n_envs,
        "device": device,
        "options": dict(options or {}),
        "steps_per_s": steps / update_s,
        "rollout_steps_per_s": steps / rollout_s,
        "update_s": update_s,
        "learner_s": learn_s,  # measured: with overlap it runs beside the rollout
        "total_s": seconds,
        "projected_3M_h": PAPER_STEPS / (steps / update_s) / 3600,
    }


def core_shares(update_s: float, rollout_s: float, learn_s: float, overlap: bool) -> dict:
    """Share of an update's wall time each of 2 cores spends on rollout, learner, nothing.

    Synchronous: one core runs the rollout, then the learner (torch uses one
    thread by policy); the second core idles (the batched highway envs run in
    the trainer process). Overlap: the rollout on one core, the learner on
    the other. Shares are wall times of each part over the update's; what
    the parts do not cover (logging, joins, waiting for a busy machine's CPU)
    shows as idle.
    """
    rollout, learner = rollout_s / update_s, learn_s / update_s
    if overlap:
        return {"core0": (rollout, 0.0), "core1": (0.0, learner)}
    return {"core0": (rollout, learner), "core1": (0.0, 0.0)}


@contextmanager
def competing_process() -> Iterator[None]:
    """A CPU-bound busy loop in another process for the duration of the block."""
    proc = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        yield
    finally:
        proc.kill()
        proc.wait()


def compile_available(device: str) -> bool:
    """torch.compile generates C++ on the CPU (needs a compiler) or Triton on CUDA."""
    return device.startswith("cuda") or shutil.which(os.environ.get("CXX", "g++")) is not None


#: Label of the row whose envs step one after another (compared with "thread policy").
PER_ENV = "per-env envs (vector sync), thread policy"
#: configs/small-learner.toml as overrides (a test keeps the two equal); the defaults.
SMALL_LEARNER = {**SMALL_MODEL, "minibatches": 4}
#: The learner rows: (label, overrides); each is compared with the first of its learner.
#: The paper learner is named (configs/paper-learner.toml), no longer the defaults.
LEARNER_ROWS = (
    ("paper learner", PAPER_LEARNER),
    ("paper learner + bf16", {**PAPER_LEARNER, "update_bf16": True}),
    ("paper learner + overlap", {**PAPER_LEARNER, "overlap": True}),
    ("paper learner + bf16 + overlap", {**PAPER_LEARNER, "update_bf16": True, "overlap": True}),
    ("small learner", SMALL_LEARNER),
    ("small learner + bf16", {**SMALL_LEARNER, "update_bf16": True}),
    ("small learner + overlap", {**SMALL_LEARNER, "overlap": True}),
    ("small learner + bf16 + overlap", {**SMALL_LEARNER, "update_bf16": True, "overlap": True}),
    # 3 PPO epochs instead of 5: 40 % less update work (learning compared in
    # docs/benchmarks/index.md, "Training throughput II").
    ("small learner + 3 epochs", {**SMALL_LEARNER, "epochs": 3}),
    ("small learner + 3 epochs + overlap", {**SMALL_LEARNER, "epochs": 3, "overlap": True}),
)
#: Row groups of ``--only`` (``demand`` is never in ``all``: it takes minutes an update;
#: ``device`` is, first, when the learner is not on the CPU).
GROUPS = ("learners", "vector", "threads", "device", "demand", "all")


#: The first device row: the default learner as it runs on the CPU today.
CPU_PATH = "small learner on cpu"


def device_rows(device: str, with_compile: bool = True) -> list[tuple[str, dict, bool]]:
    """The learner's device side by side, on the default (small) learner: the CPU path
    of today (eager update, envs in this process), then on ``device`` the eager update,
    the static update (:mod:`diacc.learn.static_update`), the static update with the
    envs in one worker process per core (what ``vector = "auto"`` picks on cuda), and
    with its loss compiled (CUDA graphs on cuda; only where a compiler or CUDA is
    present, and not on the CPU, where compiling takes minutes)."""
    cores = os.cpu_count() or 1
    on = {**SMALL_LEARNER, "device": device}
    here = {"vector": "batched"}  # the envs in this process (highway's default)
    rows = [
        (CPU_PATH, {**SMALL_LEARNER, "device": "cpu", **here}, False),
        (f"small learner on {device}: eager update", {**on, **here, "update_path": "eager"}, False),
        (
            f"small learner on {device}: static update",
            {**on, **here, "update_path": "static"},
            False,
        ),
        (
            f"small learner on {device}: static update + {cores} env workers",
            {**on, "update_path": "static", "vector": "process"},
            False,
        ),
    ]
    if with_compile and device.startswith("cuda") and compile_available(device):
        compiled = {**on, "update_path": "static", "update_compile": True, "vector": "process"}
        rows.append(
            (f"small learner on {device}: compiled static update + env workers", compiled, False)
        )
    return rows


#: The ``demand`` row: the default learner on 3600 veh/h into train-50 (480 s of demand,
#: 120 s warm-up, 600-step episodes), critic rows for 320 vehicles on the road, 24
#: minibatches (benchmarks/demand_training_speed.py's setting); 4 envs x 600 steps.
DEMAND_ROW = (
    "small learner, demand 3600 veh/h",
    {
        "env.map": "train-50", "minibatches": 24, "env.obs.max_vehicles": 320,
        "env.sim.episode_steps": 600, "env.scenario.kind": "demand",
        "env.scenario.inflow_vph": 3600.0, "env.scenario.demand_s": 480.0,
        "env.scenario.warmup_s": 120.0,
    },
    False,
)  # fmt: skip
DEMAND_ENVS, DEMAND_ROLLOUT_STEPS = 4, 600


def configurations(
    device: str, with_compile: bool, vector_only: bool = False, only: str = "all"
) -> list[tuple[str, dict, bool]]:
    """(label, config overrides, with a competing process) in the order they are run.

    The thread and vector rows run ``paper learner`` (configs/paper-learner.toml;
    "thread policy" there is that row), so that their figures stay comparable with
    the ones recorded while it was the default; ``small learner`` is the defaults
    (configs/small-learner.toml).
    """
    vector_rows = [
        (PER_ENV, {**PAPER_LEARNER, "vector": "sync"}, False),
        ("thread policy", PAPER_LEARNER, False),
    ]
    if vector_only or only == "vector":
        return vector_rows
    if only == "demand":
        return [DEMAND_ROW]
    if only == "device":
        return device_rows(device, with_compile)
    rows = [(label, options, False) for label, options in LEARNER_ROWS]
    if with_compile and compile_available(device):
        rows.append(
            ("paper learner + compiled update", {**PAPER_LEARNER, "update_compile": True}, False)
        )
    rows.append(
        (
            "paper learner, hidden 64 + concat TAIE heads",
            {**PAPER_LEARNER, **SMALL_MODEL, "model.taie_concat_heads": True},
            False,
        )
    )
    if only == "learners":
        return rows
    torch_default = {**PAPER_LEARNER, "torch_threads": os.cpu_count() or 1}
    thread_rows = [
        (f"torch default threads ({torch_default['torch_threads']})", torch_default, False),
        ("thread policy", PAPER_LEARNER, False),
        (
            f"torch default threads ({torch_default['torch_threads']}), busy CPU",
            torch_default,
            True,
        ),
        ("thread policy, busy CPU", PAPER_LEARNER, True),
    ]
    if only == "threads":
        return thread_rows
    first = device_rows(device, with_compile) if device != "cpu" else []
    return first + rows + [vector_rows[0]] + thread_rows


def select_rows(
    rows: list[tuple[str, dict, bool]], labels: tuple[str, ...]
) -> list[tuple[str, dict, bool]]:
    """The rows named in ``labels`` (all if none); ValueError naming any unknown label."""
    unknown = set(labels) - {label for label, _, _ in rows}
    if unknown:
        raise ValueError(f"no such row(s): {', '.join(sorted(unknown))}")
    return [row for row in rows if not labels or row[0] in labels]


def run(
    device: str = "cpu",
    envs: tuple[int, ...] = (16,),
    backend: str = "highway",
    variant: str = "diacc",
    updates: int = 3,
    rollout_steps: int = 50,
    with_compile: bool = True,
    vector_only: bool = False,
    only: str = "all",
    labels: tuple[str, ...] = (),
) -> list[dict]:
    """Measure every configuration (:func:`configurations`) per env count; print one table.

    ``labels``: only the rows whose label is one of these (all by default).
    Returns the rows of :func:`measure` with ``label`` and ``busy`` added.
    """
    chosen = select_rows(configurations(device, with_compile, vector_only, only), labels)
    if only == "demand":  # whole demand episodes, as a demand run trains
        envs, rollout_steps = (DEMAND_ENVS,), DEMAND_ROLLOUT_STEPS
    if updates < 2:
        raise ValueError(f"updates must be >= 2 (the first one is not timed), got {updates}")
    load_before = os.getloadavg()
    rows = []
    for n_envs in envs:
        for label, options, busy in chosen:
            with competing_process() if busy else _nothing():
                row = measure(
                    variant, backend, n_envs, updates, device, rollout_steps, "auto", options
                )
            rows.append({**row, "label": label, "busy": busy})
    _print(rows, variant, backend, device, updates, rollout_steps, (load_before, os.getloadavg()))
    return rows


@contextmanager
def _nothing() -> Iterator[None]:
    yield


def _ratio(rows: list[dict], n_envs: int, key: str, label: str, base: str) -> str:
    """How many times faster ``label`` is than ``base`` in ``key`` (env-steps/s or 1/seconds)."""
    by_label = {r["label"]: r for r in rows if r["envs"] == n_envs}
    if label not in by_label or base not in by_label:
        return ""
    a, b = by_label[label][key], by_label[base][key]
    return f"x{a / b:.2f}" if key.endswith("per_s") else f"x{b / a:.2f}"


def _shares(core: tuple[float, float]) -> str:
    """'rollout / learner / idle' percentages of one core."""
    rollout, learner = core
    return f"{rollout:.0%} / {learner:.0%} / {max(0.0, 1 - rollout - learner):.0%}"


def _print(rows, variant, backend, device, updates, rollout_steps, loads) -> None:
    load = " -> ".join(", ".join(f"{x:.1f}" for x in avg) for avg in loads)
    table = Table(
        title=f"training throughput: {variant} on {backend}, learner on {device}, "
        f"{os.cpu_count()} CPU cores, {updates - 1} timed update(s) of {rollout_steps} steps; "
        f"load average {load}"
    )
    for col in (
        "envs",
        "configuration",
        "env-steps/s (train)",
        "env-steps/s (rollout only)",
        "learner s / update",
        "3 M steps (h)",
        "vs. first row",
        "CPU s / update: rollout + learner",
        "env-steps/s, idle 2 cores (CPU-time model)",
        "core 0: rollout / learner / idle",
        "core 1",
    ):
        table.add_column(col, justify="right")
    for r in rows:
        base = next(b["label"] for b in rows if b["busy"] == r["busy"] and b["envs"] == r["envs"])
        table.add_row(
            str(r["envs"]),
            r["label"],
            f"{r['steps_per_s']:.0f}",
            f"{r['rollout_steps_per_s']:.0f}",
            f"{r['learner_s']:.2f}",
            f"{r['projected_3M_h']:.1f}",
            _ratio(rows, r["envs"], "steps_per_s", r["label"], base),
            f"{r['rollout_cpu_s']:.2f} + {r['learner_cpu_s']:.2f}",
            f"{r['idle_steps_per_s']:.0f}",
            _shares(r["core0"]),
            _shares(r["core1"]),
        )
    Console(width=200).print(table)
    for n_envs in sorted({r["envs"] for r in rows}):
        train = _ratio(rows, n_envs, "steps_per_s", "thread policy", PER_ENV)
        rollout = _ratio(rows, n_envs, "rollout_steps_per_s", "thread policy", PER_ENV)
        if train:
            print(
                f"{n_envs} envs: env-steps/s of the default vector env over per-env envs: "
                f"{train} (train), {rollout} (rollout only)"
            )
        for label in [r["label"] for r in rows if r["envs"] == n_envs]:
            if label.startswith("small learner on ") and label != CPU_PATH:
                speed = _ratio(rows, n_envs, "steps_per_s", label, CPU_PATH)
                learner_s = _ratio(rows, n_envs, "learner_s", label, CPU_PATH)
                if speed:
                    print(
                        f"{n_envs} envs: {label} over {CPU_PATH}: {speed} env-steps/s, "
                        f"{learner_s} learner speed"
                    )
        for learner in ("paper learner", "small learner"):
            for label, _ in LEARNER_ROWS:
                if label.startswith(learner + " +"):
                    ratio = _ratio(rows, n_envs, "steps_per_s", label, learner)
                    if ratio:
                        print(f"{n_envs} envs: {label} over {learner}: {ratio} env-steps/s")


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--device",
        choices=("auto", "cpu", "cuda"),
        default=TrainConfig.device,
        help="torch device of the PPO update, as 'diacc train --device' (auto: cuda if "
        "this machine has it, else cpu)",
    )
    p.add_argument("--envs", type=int, nargs="+", default=[16])
    p.add_argument("--backend", default="highway")
    p.add_argument("--variant", default="diacc")
    p.add_argument("--updates", type=int, default=3, help="per configuration; the first is untimed")
    p.add_argument("--rollout-steps", type=int, default=50)
    p.add_argument("--no-compile", action="store_true", help="skip the compiled-update row")
    p.add_argument(
        "--vector-only", action="store_true", help="only per-env vs batched envs (two rows)"
    )
    p.add_argument("--only", choices=GROUPS, default="all", help="rows of one group only")
    p.add_argument(
        "--rows",
        default="",
        help="comma-separated row labels: only these (e.g. 'small learner,small learner + "
        "overlap')",
    )
    p.add_argument(
        "--profile",
        action="store_true",
        help="per-module profile of one PPO update instead "
        "(diacc.experiments.bench.update_profile)",
    )
    args = p.parse_args(argv)
    # a missing CUDA device fails before any row runs; the table names cpu or cuda, not auto
    device = str(resolve_device(args.device))
    if args.profile:
        from diacc.experiments.bench import update_profile

        update_profile.main(
            ["--envs", str(args.envs[0]), "--rollout-steps", str(args.rollout_steps)]
        )
        return
    rows = tuple(label.strip() for label in args.rows.split(",") if label.strip())
    try:  # checked before the first row runs
        select_rows(configurations(device, not args.no_compile, args.vector_only, args.only), rows)
    except ValueError as exc:
        p.error(f"--rows: {exc}")
    run(
        device,
        tuple(args.envs),
        args.backend,
        args.variant,
        args.updates,
        args.rollout_steps,
        not args.no_compile,
        args.vector_only,
        args.only,
        rows,
    )


if __name__ == "__main__":
    try:
        main()
    except DiaccError as exc:
        sys.exit(f"diacc bench: error: {exc}")
