"""End-to-end training throughput: rollout + PPO update, env-steps per second.

Runs a few real updates of :func:`diacc.algo.mappo.train` per configuration,
in this process, one configuration after another in one run, and projects the
wall time of the paper's 3 M-step run from the measured rate:

* ``per-env envs``: the environments stepped one after another, each with
  its own simulator (``vector = "sync"``, the path before batching), next to
  ``thread policy``, where ``highway`` runs all envs on one batched simulator
  (``vector = "auto"`` = ``"batched"``; :class:`diacc.vector.BatchedVectorEnv`);
* ``torch default threads``: one intra-op thread per core (torch's own
  default, what diacc did before it had a thread policy);
* ``thread policy``: :func:`diacc.threads.default_threads`;
* ``+ bf16 update`` / ``+ compiled update``: the learner options
  ``update_bf16`` / ``update_compile`` (compile only where a C++ compiler or
  CUDA is present; the first update, which compiles, is not timed);
* ``+ hidden 64`` (GAT, MLP and GRU widths 64 instead of 128) and ``+ concat
  TAIE heads`` (``model.taie_concat_heads``): the cheaper learners;
* the first two again **with a competing CPU-bound process** (a busy loop
  started for their duration), which is where thread counts matter.

The first update of every configuration pays start-up and is left out. The
learner share per update is the update's time minus its rollout's (GAE,
batching and ``epochs`` PPO passes). ``--device cuda`` puts the learner on
CUDA (rollouts stay on the CPU).

``python -m diacc.bench.training --device cuda --envs 4 --updates 3``;
``--vector-only`` measures the first two rows alone (per-env vs batched envs).
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

from diacc.algo import mappo
from diacc.algo.mappo import train
from diacc.config import EnvConfig, TrainConfig, override
from diacc.errors import DiaccError

PAPER_STEPS = 3_000_000
#: The smaller networks of the learner-cost rows (the paper: hidden sizes "of the order 64-256").
SMALL_MODEL = {"model.hidden_dim": 64, "model.gru_hidden": 64}
#: Rows "thread policy + <option>" whose learner time is compared with "thread policy".
LEARNER_OPTIONS = ("bf16 update", "compiled update", "hidden 64", "hidden 64 + concat TAIE heads")


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

    ``options`` are further config overrides (``torch_threads``, ``update_bf16``, ...).
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
    return {
        "variant": variant,
        "backend": backend,
        "envs": n_envs,
        "device": device,
        "options": dict(options or {}),
        "steps_per_s": steps / update_s,
        "rollout_steps_per_s": steps / rollout_s,
        "update_s": update_s,
        "learner_s": update_s - rollout_s,
        "total_s": seconds,
        "projected_3M_h": PAPER_STEPS / (steps / update_s) / 3600,
    }


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


def configurations(
    device: str, with_compile: bool, vector_only: bool = False
) -> list[tuple[str, dict, bool]]:
    """(label, config overrides, with a competing process) in the order they are run."""
    vector_rows = [(PER_ENV, {"vector": "sync"}, False), ("thread policy", {}, False)]
    if vector_only:
        return vector_rows
    torch_default = {"torch_threads": os.cpu_count() or 1}
    rows = [
        (f"torch default threads ({torch_default['torch_threads']})", torch_default, False),
        ("thread policy", {}, False),
        vector_rows[0],
        ("thread policy + bf16 update", {"update_bf16": True}, False),
    ]
    if with_compile and compile_available(device):
        rows.append(("thread policy + compiled update", {"update_compile": True}, False))
    rows += [
        ("thread policy + hidden 64", SMALL_MODEL, False),
        (
            "thread policy + hidden 64 + concat TAIE heads",
            {**SMALL_MODEL, "model.taie_concat_heads": True},
            False,
        ),
    ]
    rows += [
        (
            f"torch default threads ({torch_default['torch_threads']}), busy CPU",
            torch_default,
            True,
        ),
        ("thread policy, busy CPU", {}, True),
    ]
    return rows


def run(
    device: str = "cpu",
    envs: tuple[int, ...] = (4,),
    backend: str = "highway",
    variant: str = "diacc",
    updates: int = 3,
    rollout_steps: int = 50,
    with_compile: bool = True,
    vector_only: bool = False,
) -> list[dict]:
    """Measure every configuration (:func:`configurations`) per env count; print one table.

    Returns the rows of :func:`measure` with ``label`` and ``busy`` added.
    """
    if updates < 2:
        raise ValueError(f"updates must be >= 2 (the first one is not timed), got {updates}")
    rows = []
    for n_envs in envs:
        for label, options, busy in configurations(device, with_compile, vector_only):
            with competing_process() if busy else _nothing():
                row = measure(
                    variant, backend, n_envs, updates, device, rollout_steps, "auto", options
                )
            rows.append({**row, "label": label, "busy": busy})
    _print(rows, variant, backend, device, updates, rollout_steps)
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


def _print(rows, variant, backend, device, updates, rollout_steps) -> None:
    table = Table(
        title=f"training throughput: {variant} on {backend}, learner on {device}, "
        f"{os.cpu_count()} CPU cores, {updates - 1} timed update(s) of {rollout_steps} steps"
    )
    for col in (
        "envs",
        "configuration",
        "env-steps/s (train)",
        "env-steps/s (rollout only)",
        "learner s / update",
        "3 M steps (h)",
        "vs. first row",
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
        )
    Console(width=160).print(table)
    for n_envs in sorted({r["envs"] for r in rows}):
        train = _ratio(rows, n_envs, "steps_per_s", "thread policy", PER_ENV)
        rollout = _ratio(rows, n_envs, "rollout_steps_per_s", "thread policy", PER_ENV)
        if train:
            print(
                f"{n_envs} envs: env-steps/s of the default vector env over per-env envs: "
                f"{train} (train), {rollout} (rollout only)"
            )
        for option in LEARNER_OPTIONS:
            ratio = _ratio(rows, n_envs, "learner_s", f"thread policy + {option}", "thread policy")
            if ratio:
                print(f"{n_envs} envs: learner speed-up of {option} over the default: {ratio}")


def profile_update(
    n_envs: int = 4, rollout_steps: int = 50, bf16: bool = False, top: int = 15
) -> str:
    """torch.profiler table of one PPO pass (``epochs`` = 1) on a real rollout batch."""
    import torch

    from diacc.algo import mappo
    from diacc.threads import set_torch_threads

    cfg = override(
        TrainConfig(),
        {
            "n_envs": n_envs,
            "rollout_steps": rollout_steps,
            "env.sim.episode_steps": min(rollout_steps, EnvConfig().sim.episode_steps),
            "device": "cpu",
            "epochs": 1,
        },
    )
    cfg = override(cfg, {"update_bf16": bf16})
    mappo.seed_everything(cfg.seed)
    set_torch_threads(cfg.torch_threads)
    agent = mappo.make_agent(cfg, torch.device("cpu"))
    envs = mappo.make_vector_env(cfg.env, n_envs, cfg.seed)
    try:
        roll, next_value, _ = mappo.collect_rollout(agent, envs, cfg, 0)
    finally:
        envs.close()
    advantages, returns = mappo.rollout_gae(roll, next_value, cfg)
    batch = mappo.make_batch(roll, advantages, returns, cfg.chunk_len, torch.device("cpu"))
    with torch.profiler.profile() as prof:
        mappo.ppo_update(agent, batch, cfg, envs.n_cavs)
    return prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=top)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--envs", type=int, nargs="+", default=[4])
    p.add_argument("--backend", default="highway")
    p.add_argument("--variant", default="diacc")
    p.add_argument("--updates", type=int, default=3, help="per configuration; the first is untimed")
    p.add_argument("--rollout-steps", type=int, default=50)
    p.add_argument("--no-compile", action="store_true", help="skip the compiled-update row")
    p.add_argument(
        "--vector-only", action="store_true", help="only per-env vs batched envs (two rows)"
    )
    p.add_argument(
        "--profile", action="store_true", help="profile one PPO pass (fp32, then bf16) instead"
    )
    args = p.parse_args(argv)
    mappo.resolve_device(args.device)  # a missing CUDA device fails before any row runs
    if args.profile:
        for bf16 in (False, True):
            print(
                f"PPO pass on a real batch ({args.envs[0]} envs x {args.rollout_steps} steps), "
                f"bf16 = {bf16}"
            )
            print(profile_update(args.envs[0], args.rollout_steps, bf16))
        return
    run(
        args.device,
        tuple(args.envs),
        args.backend,
        args.variant,
        args.updates,
        args.rollout_steps,
        not args.no_compile,
        args.vector_only,
    )


if __name__ == "__main__":
    try:
        main()
    except DiaccError as exc:
        sys.exit(f"diacc bench: error: {exc}")
