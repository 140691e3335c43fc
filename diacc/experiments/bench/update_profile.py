"""Where the PPO update spends its time: per module, forward vs backward, per epoch.

The update is the learner's whole cost and it scales with samples, so this
profile decides what to make cheaper. It collects one real rollout (highway,
the default scenario), cuts it into the update's batch and runs
:func:`diacc.learn.ppo.ppo_update` once with timing hooks on the networks'
parts (embeddings, the GATs, context/fusion MLPs, cross-attention, GRU cells,
heads). Forward time of a part runs from its forward pre-hook to its forward
hook; backward time from its backward pre-hook (gradient of the output ready)
to its backward hook (gradients of its inputs done). A timed part's float
inputs are made to require gradients (a detached copy) so that its backward
hook fires after its own weight gradients even where it reads raw
observations: that adds one input gradient per first layer, the same work in
every configuration, and no gradient flows into the stored batch.

Times are CPU seconds of the learner thread (``time.thread_time``): the
learner runs on one thread, so they are its work, and they stay comparable on
a machine shared with other jobs, where wall-clock times swing with the load.
Hooks add a few microseconds per call.

``python -m diacc.experiments.bench.update_profile --envs 16 --rollout-steps 50``
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager

import torch
from torch import nn

from diacc.config import PAPER_LEARNER, EnvConfig, TrainConfig, override
from diacc.envs.vector import make_vector_env
from diacc.learn import ppo
from diacc.learn.agent import Agent, make_agent
from diacc.learn.buffer import make_batch
from diacc.learn.trainer import seed_everything
from diacc.threads import set_torch_threads

#: Networks' parts that are timed, by attribute path from the actor / critic.
ACTOR_PARTS = (
    "encoder.taie.hdv_embed",
    "encoder.taie.cav_embed",
    "encoder.taie.hdv_gat",
    "encoder.taie.cav_gat",
    "encoder.taie.context",
    "encoder.taie.fusion",
    "gru",
    "head",
)
CRITIC_PARTS = (
    "encoder.road_mlp",
    "encoder.traffic_mlp",
    "encoder.node_embed",
    "encoder.gat",
    "encoder.cross",
    "gru",
    "head",
)


class PartTimer:
    """Accumulates forward and backward seconds per named module (see module docstring)."""

    def __init__(self) -> None:
        self.seconds: dict[tuple[str, str], float] = defaultdict(float)
        self.calls: dict[tuple[str, str], int] = defaultdict(int)
        self._starts: dict[tuple[str, str], list[float]] = defaultdict(list)
        self._handles: list = []

    def _start(self, key: tuple[str, str]) -> None:
        self._starts[key].append(time.thread_time())

    def _stop(self, key: tuple[str, str]) -> None:
        if self._starts[key]:
            self.seconds[key] += time.thread_time() - self._starts[key].pop()
            self.calls[key] += 1

    def attach(self, name: str, module: nn.Module) -> None:
        fwd, bwd = (name, "forward"), (name, "backward")

        def start_forward(_module, args):
            self._start(fwd)
            return tuple(_grad_leaf(a) for a in args)

        self._handles += [
            module.register_forward_pre_hook(start_forward),
            module.register_forward_hook(lambda *_: self._stop(fwd)),
            module.register_full_backward_pre_hook(lambda *_: self._start(bwd)),
            module.register_full_backward_hook(lambda *_: self._stop(bwd)),
        ]

    def detach(self) -> None:
        for handle in self._handles:
            handle.remove()
        self._handles.clear()


def _grad_leaf(value):
    """A float tensor that needs no gradient -> a detached copy that does (see docstring)."""
    if isinstance(value, torch.Tensor) and value.is_floating_point() and not value.requires_grad:
        return value.detach().requires_grad_(True)
    return value


def _part(net: nn.Module, path: str) -> nn.Module | None:
    module = net
    for attr in path.split("."):
        module = getattr(module, attr, None)
        if module is None:
            return None
    return module


@contextmanager
def epoch_clock(agent: Agent, laps: list[float]) -> Iterator[None]:
    """Record the wall time of each PPO epoch: ``ppo_update`` calls randperm once per epoch."""
    real = torch.randperm
    last = [time.thread_time()]

    def lap(*args, **kwargs):
        now = time.thread_time()
        laps.append(now - last[0])
        last[0] = now
        return real(*args, **kwargs)

    torch.randperm = lap
    try:
        yield
    finally:
        torch.randperm = real
        laps.append(time.thread_time() - last[0])
        del laps[0]  # before the first epoch: value-norm update


def profile(
    options: dict, n_envs: int = 16, rollout_steps: int = 50, seed: int = 1, op_table: int = 0
) -> dict[str, object]:
    """Time one ``ppo_update`` of the config ``options`` on a real rollout batch.

    Returns total, per-epoch and per-part seconds (forward and backward), the
    share of alive agent samples and, with ``op_table`` > 0, torch.profiler's
    table of that many ops of a second update (by self CPU time).
    """
    cfg = override(
        TrainConfig(),
        {
            "n_envs": n_envs,
            "rollout_steps": rollout_steps,
            "env.sim.episode_steps": min(rollout_steps, EnvConfig().sim.episode_steps),
            "device": "cpu",
            "seed": seed,
            **options,
        },
    )
    seed_everything(cfg.seed)
    set_torch_threads(cfg.torch_threads)
    agent = make_agent(cfg, torch.device("cpu"))
    envs = make_vector_env(cfg.env, n_envs, cfg.seed, cfg.vector)
    try:
        roll, next_value, _ = ppo.collect_rollout(agent, envs, cfg, 0, global_step=0)
        n_cavs = envs.n_cavs
    finally:
        envs.close()
    advantages, returns = ppo.rollout_gae(roll, next_value, cfg)
    batch = make_batch(roll, advantages, returns, cfg.chunk_len, torch.device("cpu"))
    timer = PartTimer()
    for net_name, net, parts in (
        ("actor", agent.actor, ACTOR_PARTS),
        ("critic", agent.critic, CRITIC_PARTS),
    ):
        for path in parts:
            module = _part(net, path)
            if module is not None:
                timer.attach(f"{net_name}.{path.removeprefix('encoder.')}", module)
    laps: list[float] = []
    start = time.thread_time()
    with epoch_clock(agent, laps):
        ppo.ppo_update(agent, batch, cfg, n_cavs)
    total = time.thread_time() - start
    timer.detach()
    ops = ""
    if op_table:
        with torch.profiler.profile() as prof:
            ppo.ppo_update(agent, batch, cfg, n_cavs)
        ops = prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=op_table)
    return {
        "total_s": total,
        "epochs_s": laps,
        "samples": int(batch.actions.numel()),
        "alive_share": float(batch.alive.mean()),
        "ops": ops,
        "parts": {f"{name} {kind}": s for (name, kind), s in timer.seconds.items()},
    }


def report(label: str, result: dict) -> str:
    """A plain-text table: part, seconds, share of the update, sorted by cost."""
    total = result["total_s"]
    parts = sorted(result["parts"].items(), key=lambda kv: -kv[1])
    timed = sum(s for _, s in parts)
    lines = [
        f"== {label}: one PPO update, {result['samples']} actor samples, "
        f"{total:.2f} s; epochs " + " ".join(f"{s:.2f}" for s in result["epochs_s"]) + " s; "
        f"alive agent samples {result['alive_share']:.0%}",
        f"{'part':38s} {'seconds':>8s} {'share':>6s}",
    ]
    lines += [f"{name:38s} {s:8.3f} {s / total:6.1%}" for name, s in parts]
    lines.append(
        f"{'rest (losses, optimiser, indexing, hooks)':38s} {total - timed:8.3f} "
        f"{(total - timed) / total:6.1%}"
    )
    return "\n".join(lines) + ("\n" + result["ops"] if result["ops"] else "")


#: Learners profiled by default: configs/paper-learner.toml and configs/small-learner.toml
#: (the defaults), both named so that the profile does not move with the defaults.
LEARNERS = {
    "paper learner (hidden 128, 1 minibatch)": PAPER_LEARNER,
    "small learner (hidden 64, 4 minibatches)": {
        "model.hidden_dim": 64,
        "model.gru_hidden": 64,
        "minibatches": 4,
    },
}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--envs", type=int, default=16)
    p.add_argument("--rollout-steps", type=int, default=50)
    p.add_argument("--ops", type=int, default=0, help="also list the N costliest torch ops")
    p.add_argument("--learner", choices=("paper", "small", "both"), default="both")
    p.add_argument("--no-bf16", action="store_true", help="fp32 rows only")
    args = p.parse_args(argv)
    for label, options in LEARNERS.items():
        if args.learner != "both" and not label.startswith(args.learner):
            continue
        for bf16 in (False,) if args.no_bf16 else (False, True):
            name = label + (" + bf16" if bf16 else "")
            result = profile(
                {**options, "update_bf16": bf16}, args.envs, args.rollout_steps, op_table=args.ops
            )
            print(report(name, result), flush=True)


if __name__ == "__main__":
    main()
