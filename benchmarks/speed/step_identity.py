"""Do two source trees step the same? Seeded traces of the vector env, hashed, side by side.

A speed-up of the step must not change any result (issue 24). Each tree runs,
in its own process, the training vector env under a set of settings (the
default cell, ``train-50``, own simulators, every PSAR horizon and
full-brake mode, ``paper-congestion``, masked actions, no PSAR, the demand
scenario with agent slots refilled, and SUMO), with seeded random actions;
every step's observations, rewards, PSAR outcome, episode records and the
traffic state are hashed into one digest per setting::

    git worktree add /tmp/before HEAD~3
    python benchmarks/speed/step_identity.py /tmp/before .

Prints each setting's digests and ``IDENTICAL`` or the settings that differ
(exit status 1). ``--only NAME ...`` runs some settings; about 20 s in all.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

#: name -> (``--set``-style overrides, vector mode, envs, steps)
SETTINGS: dict[str, tuple[dict, str, int, int]] = {
    "default-batched": ({}, "batched", 16, 300),
    "train50-batched": ({"map": "train-50"}, "batched", 8, 300),
    "sync": ({}, "sync", 4, 200),
    "threat": ({"psar.full_brake": "threat"}, "batched", 8, 200),
    "bound": ({"psar.full_brake": "bound"}, "batched", 8, 200),
    "stopping": ({"psar.horizon": "stopping"}, "batched", 8, 200),
    "paper": (
        {
            "psar.horizon": "paper",
            "psar.force_brake": "paper",
            "psar.coordinate_lane_changes": False,
        },
        "batched",
        8,
        200,
    ),
    "congestion": (
        {"sim.style_preset": "paper-congestion", "map": "train-50"},
        "batched",
        8,
        200,
    ),
    "masked": ({"psar_actions": "masked"}, "batched", 8, 150),
    "nopsar": ({"use_psar": False}, "batched", 8, 150),
    "demand": (
        {
            "map": "train-50",
            "scenario.kind": "demand",
            "scenario.inflow_vph": 3600.0,
            "scenario.demand_s": 120.0,
            "scenario.warmup_s": 20.0,
            "scenario.cav_slots": 16,  # the default until "every"; both trees take it
            "sim.style_preset": "zipper",
            "obs.max_vehicles": 160,
        },
        "batched",
        4,
        200,
    ),
    "sumo": ({"backend": "sumo"}, "sync", 2, 120),
}


#: What of a vector env's step is hashed, in this order, by name: the fields of the
#: step type before issue 43 made one step-result type (``VectorStep``), read from either
#: tree's step type (:func:`_step_content`). The team reward is left out: it is made of
#: hashed fields, and trees before it lack it.
STEP_CONTENT = (
    "actor_obs",
    "critic_state",
    "ego",
    "global_reward",
    "completion",
    "delay",
    "terminated",
    "truncated",
    "alive",
    "refined_action",
    "psar_rule_mask",
    "final_critic_state",
    "final_actor_obs",
    "episodes",
    "reward_terms",
    "restarted",
    "restarts",
    "slot_start",
)

#: A content's name in the other tree's step type (``restarted`` is ``crashed`` in
#: ``diacc.envs.step.Transition``).
OTHER_NAME = {"restarted": "crashed"}


def _step_content(step) -> dict:
    """``step``'s :data:`STEP_CONTENT` by name, whichever tree's step type holds it."""
    return {
        name: getattr(step, name if hasattr(step, name) else OTHER_NAME[name])
        for name in STEP_CONTENT
    }


def _feed(h, obj) -> None:
    """Hash ``obj`` (dataclasses, arrays with dtype and shape, dicts, sequences, scalars)."""
    if dataclasses.is_dataclass(obj):
        for f in dataclasses.fields(obj):
            h.update(f.name.encode())
            _feed(h, getattr(obj, f.name))
    elif isinstance(obj, np.ndarray):
        h.update(f"{obj.dtype}{obj.shape}".encode())
        h.update(np.ascontiguousarray(obj).tobytes())
    elif isinstance(obj, dict):
        for key in sorted(obj, key=str):
            h.update(str(key).encode())
            _feed(h, obj[key])
    elif isinstance(obj, (list, tuple)):
        for item in obj:
            _feed(h, item)
    else:
        h.update(repr(obj).encode())


def trace(name: str) -> str:
    """Digest of one setting's seeded run (in this process's ``diacc``)."""
    from diacc.config import EnvConfig, override
    from diacc.envs.vector import make_vector_env

    sets, mode, n_envs, steps = SETTINGS[name]
    envs = make_vector_env(override(EnvConfig(), sets), n_envs, 7, mode)
    rng = np.random.default_rng(3)
    h = hashlib.sha256()
    try:
        _feed(h, envs.reset(first_episode=0))
        for _ in range(steps):
            actions = rng.choice(5, size=(n_envs, envs.n_cavs), p=(0.5, 0.05, 0.05, 0.2, 0.2))
            for name, value in _step_content(envs.step(actions)).items():
                h.update(name.encode())  # as a dataclass field (digests of older scripts)
                _feed(h, value)
            for batch, _ in envs.groups:
                _feed(h, batch.state.traffic)
    finally:
        envs.close()
    return h.hexdigest()[:16]


def traces_of(tree: Path, names: list[str]) -> dict[str, str]:
    """Digests of ``names`` computed by ``tree``'s code in a fresh process."""
    env = {**os.environ, "PYTHONPATH": str(tree.resolve()), "OMP_NUM_THREADS": "1"}
    out = subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), "--digests", *names],
        env=env,
        cwd=tree,
        capture_output=True,
        text=True,
    )
    if out.returncode != 0:
        tail = (out.stderr.strip().splitlines() or ["no output"])[-1]
        raise SystemExit(f"step_identity: tracing {tree} failed: {tail}")
    return dict(line.split() for line in out.stdout.strip().splitlines())


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("before", type=Path, nargs="?", help="source tree of the old code")
    p.add_argument("after", type=Path, nargs="?", help="source tree of the new code")
    p.add_argument("--only", nargs="+", choices=list(SETTINGS), help="run these settings")
    p.add_argument("--digests", nargs="+", help=argparse.SUPPRESS)  # the child's entry
    args = p.parse_args()
    if args.digests:
        for name in args.digests:
            print(name, trace(name), flush=True)
        return
    if args.before is None or args.after is None:
        p.error("give the two source trees")
    names = args.only or list(SETTINGS)
    before, after = traces_of(args.before, names), traces_of(args.after, names)
    differ = [n for n in names if before[n] != after[n]]
    for n in names:
        print(f"{n:16s} {before[n]}  {after[n]}  {'differs' if n in differ else 'same'}")
    print("IDENTICAL" if not differ else f"DIFFERENT: {', '.join(differ)}")
    sys.exit(1 if differ else 0)


if __name__ == "__main__":
    main()
