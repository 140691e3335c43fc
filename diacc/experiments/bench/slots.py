"""Agent slots side by side: a cap on the CAVs the policy drives against every CAV an
agent (``env.scenario.cav_slots``), on the demand scenario.

Each setting collects one real rollout (:func:`diacc.learn.ppo.collect_rollout`, as
``diacc train`` does) and runs its PPO update (:func:`diacc.learn.ppo.learn`: values,
GAE, batching and the update), from the same seed; the settings alternate,
``repeats`` times each, and the fastest of each is compared (CPU seconds of the
thread, which move least with a shared machine's load; wall seconds beside them).
Decisions are slot-steps with a CAV on the road (what the update learns from).

The memory per vehicle is read off the rollout's own arrays (their ``nbytes``): the
stored :class:`~diacc.envs.observation.layout.ActorObs` fields with an agent-slot axis
and the rollout arrays that grow with the slots, per slot and rollout step; the
:class:`~diacc.envs.observation.layout.CriticState` fields with a vehicle axis, per
critic row (``obs.max_vehicles`` of them per env) and step; the rest per env and step.

``diacc bench --agent-slots``
"""

from __future__ import annotations

import dataclasses
import os

import numpy as np
import torch
from rich.console import Console
from rich.table import Table

from diacc.config import TrainConfig, override, validate
from diacc.envs.observation.layout import ActorObs, CriticState
from diacc.envs.vector import make_vector_env
from diacc.learn import ppo
from diacc.learn.agent import make_agent
from diacc.learn.buffer import Rollout
from diacc.learn.trainer import seed_everything
from diacc.records import declared_axes
from diacc.threads import set_torch_threads

#: The demand scenario measured: 3600 veh/h into train-50 for 240 s (40 % CAVs, the
#: default share: 96 CAVs), whole 240-step episodes, critic rows for 320 vehicles,
#: the default learner on highway.
SETTING = {
    "env.backend": "highway",
    "env.map": "train-50",
    "env.scenario.kind": "demand",
    "env.scenario.inflow_vph": 3600.0,
    "env.scenario.demand_s": 240.0,
    "env.sim.episode_steps": 240,
    "env.obs.max_vehicles": 320,
}
ENVS, STEPS = 2, 240
#: The cap compared with every CAV an agent (the demand runs' setting before ``every``).
CAP = 16
EVERY = "every"


def config(slots: int | str, setting: dict, n_envs: int, steps: int, device: str) -> TrainConfig:
    """The training config of one setting: ``setting`` with ``slots`` agent slots and
    one update of ``n_envs`` x ``steps``, checked as ``diacc train`` checks it."""
    cfg = override(
        TrainConfig(),
        {
            **setting,
            "env.scenario.cav_slots": slots,
            "n_envs": n_envs,
            "rollout_steps": steps,
            "total_steps": n_envs * steps,
            "device": device,
            "run_dir": "unused",
        },
    )
    return validate(cfg)


def _slot_arrays(per_agent: bool) -> set[str]:
    """Names of the :class:`Rollout` arrays that grow with the agent slots."""

    def sizes(slots: int) -> dict[str, int]:
        roll = Rollout.allocate(1, 1, slots, 1, 1, per_agent)
        return {
            f.name: getattr(roll, f.name).nbytes
            for f in dataclasses.fields(roll)
            if isinstance(getattr(roll, f.name), np.ndarray)
        }

    one, two = sizes(1), sizes(2)
    return {name for name in one if two[name] != one[name]}


def _by_axis(records: list, cls: type, axis: str) -> tuple[int, int]:
    """(bytes of the fields whose second axis is ``axis``, bytes of the others) summed
    over ``records`` (one :class:`ActorObs` / :class:`CriticState` per step)."""
    grows = {
        name for name, axes in declared_axes(cls) if axes and axes.split(",")[1].strip() == axis
    }
    names = [name for name, _ in declared_axes(cls)]
    on_axis = sum(getattr(r, name).nbytes for r in records for name in names if name in grows)
    other = sum(getattr(r, name).nbytes for r in records for name in names if name not in grows)
    return on_axis, other


def buffer_bytes(roll: Rollout) -> dict[str, float]:
    """Bytes of the rollout's stored steps (observations and arrays; not the state
    after the last step nor cut episodes' final states), from their arrays: per agent
    slot and step, per critic vehicle row and step, per env and step, and ``total``."""
    S, E, C = roll.alive.shape
    N = roll.critic_state[0].nodes.shape[1]
    slot_obs, env_obs = _by_axis(roll.actor_obs, ActorObs, "C")
    row_obs, env_critic = _by_axis(roll.critic_state, CriticState, "N")
    per_slot = _slot_arrays(per_agent=roll.values.ndim == 3)
    arrays = {
        f.name: getattr(roll, f.name).nbytes
        for f in dataclasses.fields(roll)
        if isinstance(getattr(roll, f.name), np.ndarray)
    }
    slot_arrays = sum(n for name, n in arrays.items() if name in per_slot)
    env_arrays = sum(n for name, n in arrays.items() if name not in per_slot)
    out = {
        "slot_obs_B": slot_obs / (S * E * C),
        "slot_arrays_B": slot_arrays / (S * E * C),
        "critic_row_B": row_obs / (S * E * N),
        "env_B": (env_obs + env_critic + env_arrays) / (S * E),
        "slot_steps_B": slot_obs + slot_arrays,
        "total_B": slot_obs + slot_arrays + row_obs + env_obs + env_critic + env_arrays,
    }
    out["slot_B"] = out["slot_obs_B"] + out["slot_arrays_B"]
    return out


def measure(
    slots: int | str,
    setting: dict | None = None,
    n_envs: int = ENVS,
    steps: int = STEPS,
    device: str = "cpu",
) -> dict:
    """One rollout of ``setting`` with ``slots`` agent slots and its PPO update."""
    cfg = config(slots, SETTING if setting is None else setting, n_envs, steps, device)
    seed_everything(cfg.seed)
    set_torch_threads(cfg.torch_threads)
    learner = torch.device(device)
    agent = make_agent(cfg, learner)
    envs = make_vector_env(cfg.env, cfg.n_envs, cfg.seed, cfg.vector)
    try:
        roll, next_value, stats = ppo.collect_rollout(agent, envs, cfg, 0, 0, values=False)
        n_cavs = envs.n_cavs
    finally:
        envs.close()
    _, losses = ppo.learn(agent, roll, next_value, cfg, learner, n_cavs)
    return {
        "slots": slots,
        "C": n_cavs,
        "steps": steps,
        "envs": n_envs,
        "max_vehicles": cfg.env.obs.max_vehicles,
        "decisions": int(roll.alive.sum()),
        "most_on_road": int(roll.alive.sum(-1).max()),
        "rollout_s": stats.seconds,
        "rollout_cpu_s": stats.cpu_seconds,
        "update_s": losses["learner_s"],
        "update_cpu_s": losses["learner_cpu_s"],
        **buffer_bytes(roll),
    }


#: Figures compared as every / cap (:func:`ratios`).
RATIO_KEYS = ("rollout_cpu_s", "update_cpu_s", "decisions", "slot_steps_B")


def fastest(rows: list[dict], slots: int | str) -> dict:
    """The row of ``slots`` with the least rollout + update CPU seconds."""
    return min(
        (r for r in rows if r["slots"] == slots),
        key=lambda r: r["rollout_cpu_s"] + r["update_cpu_s"],
    )


def ratios(rows: list[dict], cap: int | str = CAP) -> dict[str, float]:
    """Every CAV an agent over the cap, key by key, of each one's fastest row."""
    every, capped = fastest(rows, EVERY), fastest(rows, cap)
    return {key: every[key] / capped[key] for key in RATIO_KEYS}


def run(
    setting: dict | None = None,
    n_envs: int = ENVS,
    steps: int = STEPS,
    cap: int = CAP,
    repeats: int = 2,
    device: str = "cpu",
) -> tuple[list[dict], dict[str, float]]:
    """Measure the cap and every CAV, alternating, ``repeats`` times each; print a table
    and the ratios. Returns the rows of :func:`measure` and :func:`ratios`."""
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    load_before = os.getloadavg()
    rows = [
        measure(slots, setting, n_envs, steps, device)
        for _ in range(repeats)
        for slots in (cap, EVERY)
    ]
    result = ratios(rows, cap)
    _print(rows, result, cap, device, (load_before, os.getloadavg()))
    return rows, result


def _span(rows: list[dict], key: str) -> str:
    values = [r[key] for r in rows]
    return f"{min(values):.2f}" + (f"-{max(values):.2f}" if len(values) > 1 else "")


def _print(rows, result, cap, device, loads) -> None:
    load = " -> ".join(", ".join(f"{x:.1f}" for x in avg) for avg in loads)
    first = rows[0]
    table = Table(
        title=f"agent slots: one rollout of {first['envs']} envs x {first['steps']} steps and "
        f"its PPO update, learner on {device}, {len(rows) // 2} run(s) each; "
        f"load average {load}"
    )
    for col in (
        "agent slots",
        "C",
        "CAVs at once (most)",
        "decisions",
        "rollout CPU s (wall)",
        "update CPU s (wall)",
        "B / slot / step (obs + arrays)",
        "B / critic row / step",
        "B / env / step",
        "slot-steps MiB",
    ):
        table.add_column(col, justify="right")
    for slots in (cap, EVERY):
        mine = [r for r in rows if r["slots"] == slots]
        r = fastest(rows, slots)
        table.add_row(
            f"cap {slots}" if slots != EVERY else EVERY,
            str(r["C"]),
            str(r["most_on_road"]),
            f"{r['decisions']} ({r['decisions'] / (r['steps'] * r['envs'] * r['C']):.0%})",
            f"{_span(mine, 'rollout_cpu_s')} ({_span(mine, 'rollout_s')})",
            f"{_span(mine, 'update_cpu_s')} ({_span(mine, 'update_s')})",
            f"{r['slot_B']:.0f} ({r['slot_obs_B']:.0f} + {r['slot_arrays_B']:.0f})",
            f"{r['critic_row_B']:.0f} (x {r['max_vehicles']})",
            f"{r['env_B']:.0f}",
            f"{r['slot_steps_B'] / 2**20:.1f}",
        )
    Console(width=200).print(table)
    print(
        f"every CAV an agent over cap {cap} (fastest of each): rollout "
        f"x{result['rollout_cpu_s']:.2f}, update x{result['update_cpu_s']:.2f} (CPU s) for "
        f"x{result['decisions']:.2f} the decisions; slot-step bytes x{result['slot_steps_B']:.2f}"
    )
