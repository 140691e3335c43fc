"""One PPO update on the GPU beside the CPU's, on one rollout (issue 63's targets).

    python benchmarks/speed/gpu_update.py [--device cuda] [--envs 16] [--rollout-steps 50]
                                          [--repeats 5] [--no-compile]

One seeded rollout (the default small learner, highway, ``train-50``; ``--envs``
envs x ``--rollout-steps`` steps) is collected on the CPU; then, from the same
initial weights, each path runs :func:`diacc.learn.ppo.learn` (values, GAE, batch,
update) on it:

* ``cpu eager``: today's CPU learner, the reference;
* ``<device> eager``: the eager update on the device;
* ``<device> static``: :mod:`diacc.learn.static_update` (``update_path = "static"``);
* ``<device> static compiled``: the same with ``update_compile`` (CUDA graphs on cuda);
  its first update compiles and is reported apart.

Per path: the first update's losses and how far its weights and losses are from
``cpu eager``'s (the static path draws its minibatches on the CPU, so it should
agree to float tolerance; the eager path on a GPU draws them from the GPU's
generator and does not), then the median wall seconds of ``--repeats`` further
updates of ``learn`` (synchronised). On cuda, the static
epochs run once more under ``torch.cuda.set_sync_debug_mode("warn")``: the count
of host syncs inside them (0 expected). ``--device cpu`` runs every path on the
CPU (a dry run of this script on a machine without a GPU).
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time
import warnings

import torch

from diacc.config import EnvConfig, TrainConfig, override
from diacc.envs.vector import make_vector_env
from diacc.learn import ppo, static_update
from diacc.learn.agent import make_agent
from diacc.learn.buffer import make_batch
from diacc.learn.trainer import resolve_device, seed_everything
from diacc.threads import set_torch_threads

#: Issue 63's target for one update of 16 envs x 50 steps on the GPU.
TARGET_S = 0.060


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def params(agent) -> torch.Tensor:
    nets = (agent.actor, agent.critic)
    return torch.cat([p.detach().ravel().cpu() for net in nets for p in net.parameters()])


def run_path(label, cfg, device, start, roll, n_cavs, repeats, reference):
    """The first update (losses, agreement with ``reference``) and the timed ones."""
    agent = make_agent(cfg, device)
    for name in ("actor", "critic", "value_norm"):
        getattr(agent, name).load_state_dict(getattr(start, name).state_dict())
    torch.manual_seed(0)
    synchronize(device)
    t0 = time.perf_counter()
    _, losses = ppo.learn(agent, copy.deepcopy(roll), None, cfg, device, n_cavs)
    synchronize(device)
    first_s = time.perf_counter() - t0
    weights = params(agent)
    agree = ""
    if reference is not None:
        ref_losses, ref_weights = reference
        worst = max(
            abs(losses[k] - ref_losses[k]) / max(abs(ref_losses[k]), 1e-6)
            for k in static_update.LOSS_NAMES
        )
        agree = (
            f"vs cpu eager: max rel. loss diff {worst:.2e}, "
            f"max weight diff {(weights - ref_weights).abs().max().item():.2e}"
        )
    learn_s = []
    for _ in range(repeats):
        synchronize(device)
        t0 = time.perf_counter()
        ppo.learn(agent, roll, None, cfg, device, n_cavs)
        synchronize(device)
        learn_s.append(time.perf_counter() - t0)
    median = statistics.median(learn_s)
    print(
        f"{label:28s} first update {first_s:7.3f} s; then median {median:.4f} s / update "
        f"(min {min(learn_s):.4f}; target {TARGET_S * 1000:.0f} ms: "
        f"{'met' if median <= TARGET_S else 'not met'}) {agree}",
        flush=True,
    )
    print(f"{'':28s} first-update losses {', '.join(f'{k} {v:.5g}' for k, v in losses.items())}")
    return agent, (losses, weights)


def count_syncs(agent, roll, cfg, device, n_cavs) -> int:
    """Host syncs inside the static epochs (``set_sync_debug_mode``), on cuda only."""
    next_value = ppo.rollout_values(agent.critic, agent.value_norm, roll, cfg, device)
    adv, ret = ppo.rollout_gae(roll, next_value, cfg)
    batch = make_batch(roll, adv, ret, cfg.chunk_len, device)
    returns_n = agent.value_norm.normalize(batch.returns)
    size, count = static_update.minibatch_plan(batch.critic_h0.shape[0], cfg.minibatches)
    perms = torch.stack([torch.randperm(batch.critic_h0.shape[0]) for _ in range(cfg.epochs)])
    idx, valid = static_update.padded_minibatches(perms, size, count)
    idx, valid = idx.view(-1, size).to(device), valid.view(-1, size).to(device)
    synchronize(device)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.cuda.set_sync_debug_mode("warn")
        try:
            static_update.run_epochs(agent, batch, returns_n, idx, valid, cfg, n_cavs)
        finally:
            torch.cuda.set_sync_debug_mode("default")
    syncs = [w for w in caught if "synchroniz" in str(w.message).lower()]
    for w in syncs[:5]:
        print(f"  sync: {w.filename}:{w.lineno}: {str(w.message).splitlines()[0]}")
    return len(syncs)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cuda", choices=("cpu", "cuda"))
    p.add_argument("--envs", type=int, default=16)
    p.add_argument("--rollout-steps", type=int, default=50)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--no-compile", action="store_true", help="skip the compiled static path")
    args = p.parse_args(argv)
    device = resolve_device(args.device)
    set_torch_threads(0)
    cfg = override(
        TrainConfig(),
        {
            "n_envs": args.envs,
            "rollout_steps": args.rollout_steps,
            "env.map": "train-50",
            "env.sim.episode_steps": min(args.rollout_steps, EnvConfig().sim.episode_steps),
            "device": "cpu",
        },
    )
    seed_everything(1)
    start = make_agent(cfg, torch.device("cpu"))
    envs = make_vector_env(cfg.env, cfg.n_envs, cfg.seed, cfg.vector)
    try:
        roll, _, _ = ppo.collect_rollout(start, envs, cfg, 0, 0, values=False)
    finally:
        envs.close()
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    print(
        f"# one update of {args.envs} envs x {args.rollout_steps} steps, small learner; "
        f"{device} ({name}), torch {torch.__version__}, {torch.get_num_threads()} threads"
    )
    cpu = torch.device("cpu")
    paths = [
        ("cpu eager", override(cfg, {"update_path": "eager"}), cpu),
        (f"{device} eager", override(cfg, {"update_path": "eager", "device": str(device)}), device),
        (
            f"{device} static",
            override(cfg, {"update_path": "static", "device": str(device)}),
            device,
        ),
    ]
    if device.type == "cpu":  # a dry run: "cpu eager" is the first path already
        del paths[1]
    if not args.no_compile:
        compiled = {"update_path": "static", "update_compile": True, "device": str(device)}
        paths.append((f"{device} static compiled", override(cfg, compiled), device))
    reference = None
    for label, path_cfg, path_device in paths:
        agent, result = run_path(
            label, path_cfg, path_device, start, roll, envs.n_cavs, args.repeats, reference
        )
        reference = reference or result
        if device.type == "cuda" and label == f"{device} static":
            syncs = count_syncs(agent, roll, path_cfg, device, envs.n_cavs)
            print(f"{'':28s} host syncs inside the static epochs: {syncs}", flush=True)


if __name__ == "__main__":
    main()
