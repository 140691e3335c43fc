"""Env stepping of two source trees side by side in one run (issue 24's "2x today's" target).

Times the training vector env (``diacc.experiments.bench.envbatch.time_vector``:
simulator + PSAR + observations + reward + episode metrics, automatic resets
included) of each tree in its own process, alternating the trees for
``--rounds`` rounds so that both see the same machine load, one thread each::

    git worktree add /tmp/before 2e858b3
    python benchmarks/speed/step_before_after.py /tmp/before . --envs 16 --mode batched

Prints each round's env-steps/s per tree, the ratio of the medians and the median of
the rounds' ratios (each round runs both trees back to back, under the same load).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
from pathlib import Path

TIMER = """
import sys, time, types
from diacc.config import EnvConfig
from diacc.experiments.bench import envbatch
envs, mode, steps, clock = int(sys.argv[1]), sys.argv[2], int(sys.argv[3]), sys.argv[4]
if clock == "cpu":  # the process's CPU time: what a busy shared machine disturbs least
    envbatch.time = types.SimpleNamespace(perf_counter=time.process_time)
print(envbatch.time_vector(EnvConfig(), envs, mode, steps, 0))
"""


def time_tree(tree: Path, envs: int, mode: str, steps: int, clock: str) -> float:
    """Env-steps/s of ``tree``'s vector env, measured in a fresh single-threaded process
    (per second of wall-clock or of the process's CPU time, ``clock``)."""
    env = {**os.environ, "PYTHONPATH": str(tree.resolve()), "OMP_NUM_THREADS": "1"}
    out = subprocess.run(
        [sys.executable, "-c", TIMER, str(envs), mode, str(steps), clock],
        env=env,
        cwd=tree,
        capture_output=True,
        text=True,
        check=True,
    )
    return float(out.stdout.strip().splitlines()[-1])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("before", type=Path, help="source tree of the old code")
    p.add_argument("after", type=Path, help="source tree of the new code")
    p.add_argument("--envs", type=int, default=16)
    p.add_argument("--mode", default="batched", choices=("batched", "sync"))
    p.add_argument("--timing-steps", type=int, default=200)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument(
        "--clock",
        default="wall",
        choices=("wall", "cpu"),
        help="per second of wall-clock, or of CPU time (steadier on a shared machine; the "
        "mode sync's SUMO workers would not count)",
    )
    args = p.parse_args()
    rates: dict[str, list[float]] = {"before": [], "after": []}
    print(
        f"{args.envs} envs, vector mode {args.mode}, {args.timing_steps} timed steps, "
        f"{args.clock} clock; load "
        f"{', '.join(f'{x:.1f}' for x in os.getloadavg())}"
    )
    for r in range(args.rounds):
        for name in ("before", "after"):
            rates[name].append(
                time_tree(getattr(args, name), args.envs, args.mode, args.timing_steps, args.clock)
            )
        print(
            f"round {r + 1}: before {rates['before'][-1]:.0f}  after {rates['after'][-1]:.0f} "
            "env-steps/s"
        )
    before, after = (statistics.median(rates[k]) for k in ("before", "after"))
    # A round's two trees run back to back, so the ratio within a round shares its load.
    paired = statistics.median(a / b for a, b in zip(rates["after"], rates["before"], strict=True))
    print(
        f"median: before {before:.0f}, after {after:.0f} env-steps/s: x{after / before:.2f}; "
        f"median of the rounds' ratios x{paired:.2f}; "
        f"load {', '.join(f'{x:.1f}' for x in os.getloadavg())}"
    )


if __name__ == "__main__":
    main()
