"""Network benchmark: parameter counts, rollout-step latency and update cost per variant.

Sizes follow the paper's training setup (and MAPPO practice): 20 environments x 10 CAVs, 100
rollout steps, recurrent chunks of 10, and the paper-size networks
(configs/paper-learner.toml, hidden 128; the defaults are the small learner's 64)
unless ``cfg`` says otherwise. One rollout step is the actor on every
CAV plus the critic on every environment state (no gradients); one update pass
is forward + backward of a PPO-like loss over the whole rollout replayed in
chunks, i.e. one of the 5 epochs with 1 minibatch.
"""

from __future__ import annotations

import functools
import time

import numpy as np
import torch

from diacc.config import (
    PAPER_LEARNER,
    VARIANTS,
    ModelConfig,
    ObservationConfig,
    TrainConfig,
    override,
)
from diacc.envs.observation import ObservationSpec
from diacc.learn.models.inputs import to_tensors
from diacc.learn.models.registry import build_networks, parameter_count
from diacc.learn.models.synthetic import random_actor_obs, random_critic_state


def _chunked(tensors: dict[str, torch.Tensor], chunk_len: int) -> dict[str, torch.Tensor]:
    """(steps, B, ...) -> (chunk_len, steps / chunk_len * B, ...): chunks become batch rows."""
    out = {}
    for k, v in tensors.items():
        steps, batch = v.shape[:2]
        v = v.reshape(steps // chunk_len, chunk_len, batch, *v.shape[2:])  # (n, L, B, ...)
        out[k] = v.transpose(0, 1).reshape(chunk_len, -1, *v.shape[3:])  # (L, n*B, ...)
    return out


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


@torch.no_grad()
def _rollout_step(actor, critic, obs, state, device: str) -> None:
    """Actor on every CAV and critic on every environment, as during a rollout."""
    n_agents, n_envs = obs["alive"].shape[0], state["traffic"].shape[0]
    actor(obs, actor.initial_hidden(n_agents, device), torch.zeros(n_agents, device=device))
    critic(state, critic.initial_hidden(n_envs, device), torch.zeros(n_envs, device=device))
    _sync(device)


def _update_pass(actor, critic, obs, state, actions, returns, device: str) -> None:
    """Forward + backward of a PPO-like loss over chunked sequences (L, rows, ...)."""
    chunk_len, rows_a = obs["alive"].shape[:2]
    rows_c = state["traffic"].shape[1]
    logits, _ = actor.forward_sequence(
        obs, actor.initial_hidden(rows_a, device), torch.zeros(chunk_len, rows_a, device=device)
    )
    values, _ = critic.forward_sequence(
        state, critic.initial_hidden(rows_c, device), torch.zeros(chunk_len, rows_c, device=device)
    )
    dist = torch.distributions.Categorical(logits=logits)
    loss = (
        -dist.log_prob(actions).mean()
        - 0.01 * dist.entropy().mean()
        + torch.nn.functional.huber_loss(values, returns, delta=10.0)
    )
    actor.zero_grad(set_to_none=True)
    critic.zero_grad(set_to_none=True)
    loss.backward()
    _sync(device)


def _median_time(fn, repeats: int) -> float:
    fn()  # warm-up (allocator, lazy init)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def run(
    device: str = "cpu",
    n_envs: int = 20,
    n_cavs: int = 10,
    rollout_steps: int = 100,
    chunk_len: int = 10,
    repeats: int = 3,
    cfg: ModelConfig | None = None,
    spec: ObservationSpec | None = None,
    seed: int = 0,
    threads: int | None = None,
) -> dict:
    """Measure every variant; print a rich table and return the figures.

    Returns ``{"params": {variant: (actor, critic)}, "step_ms": {variant: ms},
    "update_s": {variant: s}, "device": str, "threads": int, "sizes": {...}}``.
    ``threads`` sets torch's intra-op CPU threads for the run (on a busy machine
    one thread gives steadier figures than oversubscribed ones).
    """
    from rich.console import Console
    from rich.table import Table

    cfg = cfg or override(TrainConfig(), PAPER_LEARNER).model
    spec = spec or ObservationSpec.from_config(ObservationConfig())
    if rollout_steps % chunk_len:
        raise ValueError(
            f"rollout_steps {rollout_steps} must be a multiple of chunk_len {chunk_len}"
        )
    if threads is not None:
        torch.set_num_threads(threads)
    rng = np.random.default_rng(seed)
    torch.manual_seed(seed)
    n_agents = n_envs * n_cavs
    step_obs = to_tensors(random_actor_obs(spec, (n_agents,), rng), device)
    step_state = to_tensors(random_critic_state(spec, (n_envs,), rng), device)
    roll_obs = _chunked(
        to_tensors(random_actor_obs(spec, (rollout_steps, n_agents), rng), device), chunk_len
    )
    roll_state = _chunked(
        to_tensors(random_critic_state(spec, (rollout_steps, n_envs), rng), device), chunk_len
    )
    actions = torch.randint(0, 5, roll_obs["alive"].shape, device=device)  # (L, rows)
    returns = torch.randn(roll_state["traffic"].shape[:2], device=device)  # (L, rows)

    figures: dict = {
        "params": {},
        "step_ms": {},
        "update_s": {},
        "device": device,
        "threads": torch.get_num_threads(),
        "sizes": {
            "n_envs": n_envs,
            "n_cavs": n_cavs,
            "rollout_steps": rollout_steps,
            "chunk_len": chunk_len,
        },
    }
    for variant in VARIANTS:
        actor, critic = (net.to(device) for net in build_networks(variant, cfg, spec))
        figures["params"][variant] = (parameter_count(actor), parameter_count(critic))
        step = functools.partial(_rollout_step, actor, critic, step_obs, step_state, device)
        update = functools.partial(
            _update_pass, actor, critic, roll_obs, roll_state, actions, returns, device
        )
        figures["step_ms"][variant] = 1e3 * _median_time(step, repeats)
        figures["update_s"][variant] = _median_time(update, repeats)

    table = Table(
        title=f"networks on {device} ({torch.get_num_threads()} threads): "
        f"step = actor x {n_agents} + critic x {n_envs}; "
        f"update = fwd+bwd over {rollout_steps}x{n_envs}x{n_cavs}, chunks {chunk_len}"
    )
    for column in (
        "variant",
        "actor params",
        "critic params",
        "rollout step [ms]",
        "update pass [s]",
    ):
        table.add_column(column, justify="right")
    for variant in VARIANTS:
        a, c = figures["params"][variant]
        table.add_row(
            variant,
            f"{a:,}",
            f"{c:,}",
            f"{figures['step_ms'][variant]:.2f}",
            f"{figures['update_s'][variant]:.3f}",
        )
    Console().print(table)
    return figures


if __name__ == "__main__":
    run("cuda" if torch.cuda.is_available() else "cpu")
