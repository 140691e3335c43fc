"""Smoke test of an installed diacc wheel, run by .ci/wheel_smoke.sh outside the clone.

What a user of ``pip install diacc`` does first, each step a few seconds: the shipped
maps and agents are found, the PettingZoo env runs on both backends, a SUMO network is
built from a packaged map, a shipped agent acts, and the commands README shows work as
``diacc ...`` and ``python -m diacc ...``. Usage: ``python wheel_smoke.py CLONE`` (the
clone must not be where diacc is imported from). Prints one line per check; exits non-zero
on the first failure, else closes with CI's plain line ``smoke: N passed, 0 failed``.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import diacc
from diacc.shipped import shipped_checkpoints
from diacc.sim.backends.sumo.net import build_network
from diacc.sim.maps import available_maps, load_map

AGENT = "diacc-train50-realistic-headway-threat-s1"
STEPS = 5
passed = 0


def check(what: str, ok: bool) -> None:
    global passed
    print(f"{'ok' if ok else 'FAILED'}: {what}", flush=True)
    if not ok:
        print(f"smoke: {passed} passed, 1 failed")
        sys.exit(1)
    passed += 1


def run(*argv: str) -> str:
    """Run a command of the installed package; its output, or exit 1 showing it."""
    out = subprocess.run(argv, capture_output=True, text=True, timeout=600)
    if out.returncode != 0:
        print(out.stdout[-2000:], out.stderr[-2000:], sep="\n")
    check(" ".join(argv), out.returncode == 0)
    return out.stdout


def installed_outside(clone: Path) -> None:
    here = Path(diacc.__file__).resolve()
    check(f"diacc imported from {here.parent}, not the clone", clone not in here.parents)
    check("four shipped maps", available_maps() == ["test-25", "test-50", "train-25", "train-50"])
    in_clone = sorted(p.name for p in (clone / "checkpoints").glob("*.pt"))
    check(f"the clone's {len(in_clone)} checkpoints shipped", shipped_checkpoints() == in_clone)


def pettingzoo_env(backend: str) -> None:
    """A few random steps of README's Python API."""
    env = diacc.parallel_env(backend=backend, map="train-25", scenario={"n_vehicles": 8})
    try:
        env.reset(seed=0)
        rng = np.random.default_rng(0)
        for _ in range(STEPS):
            actions = {a: int(rng.integers(env.action_space(a).n)) for a in env.agents}
            _, rewards, *_ = env.step(actions)
        check(f"parallel_env on {backend}: {STEPS} steps, {len(rewards)} agents", bool(rewards))
    finally:
        env.close()


def shipped_agent_acts() -> None:
    """README's trained agent in Python, loaded by name from the installed package."""
    policy = diacc.load_policy(AGENT)
    env = policy.make_env(scenario={"n_vehicles": 10})
    try:
        observations, _ = env.reset(seed=0)
        policy.reset(seed=0)
        for _ in range(STEPS):
            observations, rewards, *_ = env.step(policy.act(observations))
        check(f"shipped agent {AGENT} acted {STEPS} steps", bool(rewards))
    finally:
        env.close()


def sumo_network(folder: Path) -> None:
    net, routes = build_network(load_map("train-50"), folder)
    check(f"SUMO network of the packaged train-50 map: {net.name}", net.stat().st_size > 0)


def commands(work: Path) -> None:
    grid = work / "one-cell.toml"
    grid.write_text('[product]\nmap = ["train-50"]\nn_vehicles = [10]\n')
    for backend in ("highway", "sumo"):
        out = run("diacc", "simulate", "--backend", backend, "--vehicles", "8",
                  "--episode-steps", "10")  # fmt: skip
        check(f"diacc simulate --backend {backend} printed metrics", "speed" in out.lower())
    out = run(sys.executable, "-m", "diacc", "simulate", "--vehicles", "8", "--episode-steps", "5")
    check("python -m diacc simulate", "speed" in out.lower())
    run("diacc", "eval", "--policy", AGENT, "--grid", str(grid), "--episodes", "1",
        "--episode-steps", "10", "--no-progress", "--out", str(work / "eval"))  # fmt: skip
    wrote = (work / "eval" / "episodes.csv").is_file()
    check("diacc eval of a shipped agent wrote episodes.csv", wrote)


def main() -> None:
    start = time.monotonic()
    installed_outside(Path(sys.argv[1]).resolve())
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        pettingzoo_env("highway")
        pettingzoo_env("sumo")
        shipped_agent_acts()
        sumo_network(work / "nets")
        commands(work)
    print(f"wheel smoke test: {time.monotonic() - start:.0f} s")
    print(f"smoke: {passed} passed, 0 failed")


if __name__ == "__main__":
    main()
