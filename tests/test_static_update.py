"""The static-shape PPO update (the GPU path) against the eager one, on the CPU."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from test_mappo import rollout_batch, tiny_config

from diacc.config import override
from diacc.learn import checkpoint, mappo, ppo, static_update
from diacc.learn.agent import make_agent, update_path
from diacc.learn.loss import NonFiniteError, minibatch_loss


def test_minibatch_plan_cuts_as_torch_chunk():
    """Sizes and counts of the eager path's ``randperm(n).chunk(k)``, fewer than k included."""
    for n in range(1, 40):
        for k in range(1, 9):
            chunks = torch.arange(n).chunk(k)
            size, count = static_update.minibatch_plan(n, k)
            assert (size, count) == (len(chunks[0]), len(chunks)), (n, k)
            idx, valid = static_update.padded_minibatches(torch.arange(n)[None], size, count)
            for chunk, row, weight in zip(chunks, idx[0], valid[0], strict=True):
                assert torch.equal(row[weight.bool()], chunk)
                assert not weight[len(chunk) :].any()


@pytest.fixture(scope="module", params=["team", "per_agent"])
def padded_case(request, tmp_path_factory):
    """8 sequences of 5 steps in 3 minibatches: 3 + 3 + 2, the last padded by one."""
    cfg = tiny_config(
        tmp_path_factory.mktemp("static"),
        chunk_len=5,
        minibatches=3,
        critic_values=request.param,
    )
    agent, _, batch = rollout_batch(cfg)
    assert batch.critic_h0.shape[0] == 8
    return cfg, agent, batch


def _params(agent) -> torch.Tensor:
    return torch.cat(
        [p.detach().ravel() for net in (agent.actor, agent.critic) for p in net.parameters()]
    )


def test_static_update_matches_eager(padded_case):
    """Same minibatches, same losses and the same weights after the update."""
    cfg, agent, batch = padded_case
    results = []
    for update in (ppo.ppo_update, static_update.static_ppo_update):
        a = copy.deepcopy(agent)
        torch.manual_seed(0)
        stats = update(a, copy.deepcopy(batch), cfg, 4)
        results.append((stats, _params(a), a.value_norm.running_mean.clone()))
    (eager, eager_params, eager_mean), (static, static_params, static_mean) = results
    assert eager.keys() == static.keys()
    for name in eager:
        assert static[name] == pytest.approx(eager[name], rel=1e-4, abs=1e-6), name
    assert not torch.equal(eager_params, _params(agent))  # the update moved the weights
    torch.testing.assert_close(static_params, eager_params, rtol=1e-4, atol=1e-6)
    assert torch.equal(static_mean, eager_mean)


def test_static_epochs_never_read_the_device(padded_case, monkeypatch):
    """Inside the epoch loop nothing is read back to the host: every method that would
    wait for a GPU raises here (the eager path calls several of them per minibatch)."""
    cfg, agent, batch = padded_case
    a = copy.deepcopy(agent)
    returns_n = a.value_norm.normalize(batch.returns)
    size, count = static_update.minibatch_plan(batch.critic_h0.shape[0], cfg.minibatches)
    perms = torch.stack([torch.randperm(batch.critic_h0.shape[0]) for _ in range(cfg.epochs)])
    idx, valid = static_update.padded_minibatches(perms, size, count)

    def host_read(*args, **kwargs):
        raise AssertionError("a host read inside the static epochs")

    getitem, setitem = torch.Tensor.__getitem__, torch.Tensor.__setitem__

    def no_mask(index):  # a boolean mask sizes the result from the data (a sync on a GPU)
        for part in index if isinstance(index, tuple) else (index,):
            if isinstance(part, torch.Tensor) and part.dtype == torch.bool:
                raise AssertionError("a host read inside the static epochs (boolean index)")

    def checked_getitem(self, index):
        no_mask(index)
        return getitem(self, index)

    def checked_setitem(self, index, value):
        no_mask(index)
        return setitem(self, index, value)

    for name in ("item", "tolist", "numpy", "cpu", "nonzero", "__bool__", "__float__", "__int__"):
        monkeypatch.setattr(torch.Tensor, name, host_read)
    monkeypatch.setattr(torch.Tensor, "__getitem__", checked_getitem)
    monkeypatch.setattr(torch.Tensor, "__setitem__", checked_setitem)
    monkeypatch.setattr(torch, "nonzero", host_read)
    monkeypatch.setattr(torch, "masked_select", host_read)
    records = static_update.run_epochs(
        a, batch, returns_n, idx.view(-1, size), valid.view(-1, size), cfg, 4
    )
    monkeypatch.undo()
    assert records.shape == (cfg.epochs * count, len(static_update.RECORD_NAMES))
    assert np.isfinite(records.numpy()).all()
    monkeypatch.setattr(torch.Tensor, "__bool__", host_read)
    with pytest.raises(AssertionError, match="host read"):  # the eager path does read
        ppo.ppo_update(copy.deepcopy(agent), batch, cfg, 4)


def test_non_finite_step_is_named_as_the_eager_path_names_it():
    rows = np.zeros((6, len(static_update.RECORD_NAMES)))
    static_update.check_records(rows, 3)
    rows[4, static_update.RECORD_NAMES.index("value_loss")] = np.nan
    rows[5, static_update.RECORD_NAMES.index("critic grad norm")] = np.inf
    with pytest.raises(
        NonFiniteError, match=r"non-finite value_loss \(nan\) in epoch 2, minibatch 2"
    ):
        static_update.check_records(rows, 3)
    rows[4] = 0.0
    with pytest.raises(NonFiniteError, match="gradient of the critic in epoch 2, minibatch 3"):
        static_update.check_records(rows, 3)


def test_auto_path_is_static_on_cuda_only(tmp_path):
    cfg = tiny_config(tmp_path)
    assert update_path(cfg, torch.device("cpu")) == "eager"
    assert update_path(cfg, torch.device("cuda")) == "static"
    assert update_path(override(cfg, {"update_path": "eager"}), torch.device("cuda")) == "eager"
    assert update_path(override(cfg, {"update_path": "static"}), torch.device("cpu")) == "static"


def test_learn_takes_the_configured_path(padded_case, monkeypatch):
    cfg, agent, _ = padded_case
    called = []
    monkeypatch.setattr(ppo, "static_ppo_update", lambda *a: called.append("static") or {})
    monkeypatch.setattr(ppo, "ppo_update", lambda *a: called.append("eager") or {})
    _, roll, _ = rollout_batch(cfg)
    for path in ("static", "eager", "auto"):
        ppo.learn(agent, roll, None, override(cfg, {"update_path": path}), torch.device("cpu"), 4)
    assert called == ["static", "eager", "eager"]


def test_compile_on_the_static_path_compiles_the_loss(tmp_path):
    """``update_compile`` with the static path compiles the whole minibatch loss (on CUDA
    with CUDA graphs), not the two replays; compiling itself is timed on the GPU host."""
    cfg = tiny_config(tmp_path, update_compile=True)
    static = make_agent(override(cfg, {"update_path": "static"}), torch.device("cpu"))
    assert static.static_loss is not None and static.actor_sequence is None
    eager = make_agent(cfg, torch.device("cpu"))
    assert eager.static_loss is None and eager.actor_sequence is not None


@pytest.mark.slow
def test_compiled_static_loss_matches_eager(padded_case):
    """The compiled minibatch loss (inductor on the CPU; about 4 min to compile on a
    loaded 2-core machine, hence slow) gives the uncompiled static update's weights."""
    cfg, agent, batch = padded_case
    results = []
    for compiled in (False, True):
        torch._dynamo.reset()
        a = copy.deepcopy(agent)
        if compiled:
            a.static_loss = torch.compile(minibatch_loss, dynamic=False)
        torch.manual_seed(0)
        static_update.static_ppo_update(a, copy.deepcopy(batch), cfg, 4)
        results.append(_params(a))
    torch.testing.assert_close(results[1], results[0], rtol=1e-4, atol=1e-6)


def test_a_static_training_run_ends_where_the_eager_one_does(tmp_path):
    """Through the trainer (rollouts, checkpoints, progress rows): the same seed with
    either path gives the same weights to float tolerance."""
    weights = {}
    for path in ("eager", "static"):
        cfg = tiny_config(tmp_path / path, update_path=path, minibatches=3)
        mappo.train(cfg, progress=False)
        payload = checkpoint.load_checkpoint(tmp_path / path / "run" / "checkpoint.pt")
        weights[path] = torch.cat([t.ravel() for t in payload["actor"].values()])
        assert payload["config"]["update_path"] == path
    torch.testing.assert_close(weights["static"], weights["eager"], rtol=1e-4, atol=1e-5)
