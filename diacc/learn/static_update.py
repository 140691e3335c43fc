"""The PPO update with static shapes and no host syncs: the path for a GPU.

Why a second path: on a GPU the eager update (:func:`diacc.learn.ppo.ppo_update`)
spends its time launching small kernels and waiting for the device, not
computing (16 envs x 50 steps: about 1.1 s on an H200,
benchmarks/speed/results/learner-two-trees/device-h200-16-cores.txt). Per
minibatch it reads five diagnostics and four finite checks back to the host,
the actor replay picks the rows to encode from the data (a sync, and a shape
that changes from minibatch to minibatch), and the action distribution checks
its arguments on the host. Here, with the same loss
(:func:`~diacc.learn.loss.minibatch_loss`):

* every epoch's permutation is drawn before the first step, from the CPU
  generator (or the one given), so the minibatches are the eager path's on the
  CPU; each is cut into minibatches of one size, ``ceil(N / minibatches)``
  sequences as ``torch.chunk`` cuts them, the last padded with weight-0
  sequences (:func:`padded_minibatches`): every step sees the same shapes;
* the networks size nothing from the data
  (:func:`~diacc.learn.models.shapes.static_shapes`: every actor row replayed,
  every node embedded, no vehicle slots cut), the distribution is unvalidated;
* the diagnostics, the total loss and the two gradient norms stay on the
  device, one row per step, read back once after the last epoch; a non-finite
  value is then reported at the first minibatch that had one (the eager path
  stops there; this one runs to the end, and the trainer drops the update the same way);
* with ``update_compile`` the minibatch loss is compiled whole (forward, and
  through AOTAutograd the backward), on CUDA with ``mode="reduce-overhead"``:
  CUDA graphs replayed per step instead of a launch per op
  (:func:`~diacc.learn.agent.make_agent`).

``update_path = "auto"`` (:func:`~diacc.learn.agent.update_path`) takes this path
on CUDA; ``tests/test_static_update.py`` runs it on the CPU against the eager one.
"""

from __future__ import annotations

import numpy as np
import torch

from diacc.config import TrainConfig
from diacc.learn.agent import Agent
from diacc.learn.buffer import Batch
from diacc.learn.loss import LOSS_NAMES, NonFiniteError, first_nonfinite, minibatch_loss
from diacc.learn.models.shapes import static_shapes

#: Columns of the per-step record: the diagnostics, the total loss, the gradient norms.
RECORD_NAMES = (*LOSS_NAMES, "loss", "actor grad norm", "critic grad norm")


def minibatch_plan(n_sequences: int, minibatches: int) -> tuple[int, int]:
    """(sequences per minibatch, minibatches per epoch) as ``torch.chunk`` splits
    ``n_sequences`` into ``minibatches``: chunks of ``ceil(n / k)``, which can be
    fewer than k (9 into 4: three of 3), as the eager update steps."""
    size = -(-n_sequences // minibatches)
    return size, -(-n_sequences // size)


def padded_minibatches(
    perms: torch.Tensor, size: int, count: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Permutations (P, N) cut into ``count`` minibatches of ``size``, the last padded.

    Returns sequence indices (P, count, size) (padding points at sequence 0) and
    weights (P, count, size): 1 for a real sequence, 0 for padding.
    """
    n_perms, n_sequences = perms.shape
    pad = count * size - n_sequences
    idx = torch.cat([perms, perms.new_zeros(n_perms, pad)], dim=1)
    ones, zeros = torch.ones(n_perms, n_sequences), torch.zeros(n_perms, pad)
    valid = torch.cat([ones, zeros], dim=1).to(perms.device)
    return idx.view(n_perms, count, size), valid.view(n_perms, count, size)


def static_ppo_update(
    agent: Agent,
    batch: Batch,
    cfg: TrainConfig,
    n_cavs: int,
    generator: torch.Generator | None = None,
) -> dict[str, float]:
    """``epochs`` passes of clipped PPO with one minibatch shape and one host sync.

    Same arguments and result as :func:`diacc.learn.ppo.ppo_update`; the
    minibatches are drawn from ``generator``, or torch's global CPU generator.
    """
    device = batch.returns.device
    agent.value_norm.update(batch.returns)
    returns_n = agent.value_norm.normalize(batch.returns)  # (L, B_c[, C])
    n_sequences = batch.critic_h0.shape[0]
    size, count = minibatch_plan(n_sequences, cfg.minibatches)
    draw_on = torch.device("cpu") if generator is None else generator.device
    perms = torch.stack(
        [
            torch.randperm(n_sequences, device=draw_on, generator=generator)
            for _ in range(cfg.epochs)
        ]
    )  # (epochs, N)
    idx, valid = padded_minibatches(perms, size, count)  # (epochs, count, size) each
    idx = idx.view(-1, size).to(device)  # (steps, size)
    valid = valid.view(-1, size).to(device)
    records = run_epochs(agent, batch, returns_n, idx, valid, cfg, n_cavs)  # (steps, 8)
    params = [p for net in (agent.actor, agent.critic) for p in net.parameters()]
    params_finite = torch.stack([torch.isfinite(p).all() for p in params]).all()
    read = torch.cat([records.flatten(), params_finite.float()[None]]).cpu().numpy()
    rows = read[:-1].reshape(records.shape)  # the update's one sync (steps, 8)
    check_records(rows, count)
    if not read[-1]:
        for part, net in (("actor", agent.actor), ("critic", agent.critic)):
            bad = first_nonfinite(net, part)
            if bad is not None:
                raise NonFiniteError(f"non-finite parameter {bad} after the optimiser step")
    return {name: float(np.mean(rows[:, i])) for i, name in enumerate(LOSS_NAMES)}


def run_epochs(
    agent: Agent,
    batch: Batch,
    returns_n: torch.Tensor,
    idx: torch.Tensor,
    valid: torch.Tensor,
    cfg: TrainConfig,
    n_cavs: int,
) -> torch.Tensor:
    """One optimiser step per row of ``idx`` / ``valid`` (steps, size); nothing read back.

    Returns the record (steps, :data:`RECORD_NAMES`) on the batch's device.
    """
    loss_fn = agent.static_loss or minibatch_loss
    records = torch.empty(len(idx), len(RECORD_NAMES), device=idx.device)
    with static_shapes():
        for step in range(len(idx)):
            if agent.static_loss is not None:  # CUDA graphs: a new step, earlier outputs read
                torch.compiler.cudagraph_mark_step_begin()
            parts = loss_fn(agent, batch, returns_n, idx[step], cfg, n_cavs, valid[step])
            agent.optimizer.zero_grad()
            parts.loss.backward()
            norms = [
                torch.nn.utils.clip_grad_norm_(net.parameters(), cfg.max_grad_norm)
                for net in (agent.actor, agent.critic)
            ]
            agent.optimizer.step()
            records[step] = torch.cat(
                [parts.stacked(), parts.loss.detach()[None], torch.stack(norms)]
            )
    return records


def check_records(rows: np.ndarray, per_epoch: int) -> None:
    """Raise :class:`NonFiniteError` at the first step whose loss or gradient norm was
    not finite, in the eager path's words (its epoch and minibatch)."""
    checked = (
        "policy_loss",
        "value_loss",
        "entropy",
        "loss",
        "actor grad norm",
        "critic grad norm",
    )
    columns = [RECORD_NAMES.index(name) for name in checked]
    bad_steps = np.flatnonzero(~np.isfinite(rows[:, columns]).all(axis=1))
    if not len(bad_steps):
        return
    step = int(bad_steps[0])
    where = f"epoch {step // per_epoch + 1}, minibatch {step % per_epoch + 1}"
    for name, column in zip(checked, columns, strict=True):
        if not np.isfinite(rows[step, column]):
            if name.endswith("grad norm"):
                raise NonFiniteError(f"non-finite gradient of the {name.split()[0]} in {where}")
            raise NonFiniteError(f"non-finite {name} ({rows[step, column]}) in {where}")
