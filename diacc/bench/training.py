"""End-to-end training throughput: rollout + PPO update, env-steps per second.

Runs a few real updates of :func:`diacc.algo.mappo.train` for each
environment count, in this process, and projects the wall time of the
paper's 3 M-step run from the measured rate.

``python -m diacc.bench.training --device cuda --envs 1 4 20``
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from rich.console import Console
from rich.table import Table

from diacc.algo.mappo import train
from diacc.config import TrainConfig, override

PAPER_STEPS = 3_000_000


def measure(
    variant: str,
    backend: str,
    n_envs: int,
    updates: int,
    device: str,
    rollout_steps: int = 100,
    vector: str = "auto",
) -> dict:
    """Train ``updates`` updates; return env-steps/s of the whole loop and of rollouts."""
    with tempfile.TemporaryDirectory() as tmp:
        cfg = override(
            TrainConfig(),
            {
                "variant": variant,
                "backend": backend,
                "n_envs": n_envs,
                "device": device,
                "rollout_steps": rollout_steps,
                "total_steps": updates * rollout_steps * n_envs,
                "run_dir": tmp,
                "checkpoint_every": 10_000,
                "vector": vector,
            },
        )
        start = time.perf_counter()
        train(cfg, progress=False)
        seconds = time.perf_counter() - start
        records = [
            json.loads(line) for line in (Path(tmp) / "progress.jsonl").read_text().splitlines()
        ]
    # The first update pays for start-up (imports, worker spawn); report the steady state.
    steady = records[1:] or records
    update_s = sum(1.0 / r["updates_per_s"] for r in steady) / len(steady)
    steps = rollout_steps * n_envs
    return {
        "variant": variant,
        "backend": backend,
        "envs": n_envs,
        "device": device,
        "steps_per_s": steps / update_s,
        "rollout_steps_per_s": sum(r["env_steps_per_s"] for r in steady) / len(steady),
        "update_s": update_s,
        "total_s": seconds,
        "projected_3M_h": PAPER_STEPS / (steps / update_s) / 3600,
    }


def run(
    device: str = "cpu",
    envs: tuple[int, ...] = (1, 4, 20),
    backend: str = "highway",
    variant: str = "diacc",
    updates: int = 2,
) -> list[dict]:
    rows = [measure(variant, backend, n, updates, device) for n in envs]
    table = Table(title=f"training throughput: {variant} on {backend}, device {device}")
    for col in (
        "envs",
        "env-steps/s (train)",
        "env-steps/s (rollout only)",
        "s / update",
        "3 M steps (h)",
    ):
        table.add_column(col, justify="right")
    for r in rows:
        table.add_row(
            str(r["envs"]),
            f"{r['steps_per_s']:.0f}",
            f"{r['rollout_steps_per_s']:.0f}",
            f"{r['update_s']:.1f}",
            f"{r['projected_3M_h']:.1f}",
        )
    Console().print(table)
    return rows


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--envs", type=int, nargs="+", default=[1, 4, 20])
    p.add_argument("--backend", default="highway")
    p.add_argument("--variant", default="diacc")
    p.add_argument("--updates", type=int, default=2)
    args = p.parse_args(argv)
    run(args.device, tuple(args.envs), args.backend, args.variant, args.updates)


if __name__ == "__main__":
    main()
