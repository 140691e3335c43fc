"""Training-throughput options: thread policy, rollout/learner devices, bf16 and compile."""

from __future__ import annotations

import copy
import multiprocessing as mp
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from test_mappo import tiny_config

from diacc.config import (
    ConfigError,
    ModelConfig,
    ObservationConfig,
    TrainConfig,
    override,
    validate,
)
from diacc.envs.observation import ObservationSpec
from diacc.learn import agent as agent_module
from diacc.learn import buffer, checkpoint, mappo, ppo, trainer
from diacc.learn.models.inputs import to_tensors
from diacc.learn.models.layers import embed_all, embed_present, mlp
from diacc.learn.models.registry import build_networks
from diacc.learn.models.synthetic import random_actor_obs, random_critic_state
from diacc.threads import (
    WORKER_THREAD_VARS,
    default_threads,
    set_torch_threads,
    worker_env,
    worker_environment,
)

SMALL = ModelConfig(hidden_dim=32, gru_hidden=32, cross_dim=32)
TINY_NETS = {"model.hidden_dim": 16, "model.gru_hidden": 16, "model.cross_dim": 16}


# ----------------------------------------------------------------------------- threads
def test_default_thread_rule():
    assert [default_threads(c) for c in (1, 2, 3, 4, 16, 64)] == [1, 1, 1, 2, 8, 8]


def test_set_torch_threads_applies_rule_and_override():
    before = torch.get_num_threads()
    try:
        assert set_torch_threads(0) == default_threads() == torch.get_num_threads()
        assert set_torch_threads(2) == 2
        with pytest.raises(ValueError, match="torch threads must be >= 0"):
            set_torch_threads(-1)
    finally:
        torch.set_num_threads(before)


def test_thread_config_is_validated():
    with pytest.raises(ConfigError, match=r"'torch_threads' must be in \[0, 1024\]"):
        validate(override(TrainConfig(), {"torch_threads": "-2"}))
    assert validate(override(TrainConfig(), {"torch_threads": "3"})).torch_threads == 3


def _report_env(conn) -> None:
    conn.send({name: os.environ.get(name) for name in WORKER_THREAD_VARS})


def test_spawned_workers_get_one_library_thread(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "7")
    monkeypatch.delenv("MKL_NUM_THREADS", raising=False)
    assert worker_env({"OMP_NUM_THREADS": "7"})["OMP_NUM_THREADS"] == "1"
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_report_env, args=(child,))
    with worker_environment():
        proc.start()
    seen = parent.recv()
    proc.join(timeout=30)
    assert seen == {name: "1" for name in WORKER_THREAD_VARS}
    # the parent's own settings are back as they were
    assert os.environ["OMP_NUM_THREADS"] == "7" and "MKL_NUM_THREADS" not in os.environ


# ----------------------------------------------------------------------------- compile
def test_embed_all_matches_embed_present_with_gradients():
    torch.manual_seed(0)
    embed = mlp(6, 16, 16, 0.2)
    nodes = torch.randn(30, 7, 6)  # (M, K, F)
    mask = torch.rand(30, 7) < 0.4  # (M, K)
    outs, grads = [], []
    for fn in (embed_present, embed_all):
        embed.zero_grad()
        out = fn(embed, nodes, mask)
        (out * torch.linspace(-1, 1, 16)).sum().backward()
        outs.append(out.detach())
        grads.append(torch.cat([p.grad.ravel() for p in embed.parameters()]))
    assert torch.equal(outs[1][~mask], torch.zeros_like(outs[1][~mask]))
    torch.testing.assert_close(outs[0], outs[1], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-5, atol=1e-6)
    # NaN padding reaches neither output nor weight gradients (0 x NaN would).
    embed.zero_grad()
    embed_all(embed, nodes.masked_fill(~mask[..., None], float("nan")), mask).sum().backward()
    assert all(torch.isfinite(p.grad).all() for p in embed.parameters())


def _chunk_inputs(make_obs, net, rng, spec: ObservationSpec, rows: int):
    """Sequence-replay inputs (L=4, rows, ...) of ``net`` from ``make_obs``."""
    inputs = to_tensors(make_obs(spec, (4, rows), rng))
    return inputs, torch.zeros(rows, net.hidden_size), torch.zeros(4, rows, dtype=torch.bool)


@pytest.mark.parametrize("variant", ["diacc", "mappo"])
def test_sequence_replay_traces_without_graph_breaks(variant):
    """torch.compile sees one graph per network (dynamo tracing only; no code generation)."""
    spec, rng = ObservationSpec.from_config(ObservationConfig()), np.random.default_rng(0)
    makers = (random_actor_obs, random_critic_state)
    for net, make_obs in zip(build_networks(variant, SMALL, spec), makers, strict=True):
        torch._dynamo.reset()
        args = _chunk_inputs(make_obs, net, rng, spec, 6)
        explained = torch._dynamo.explain(net.forward_sequence)(*args)
        assert explained.graph_break_count == 0, [b.reason for b in explained.break_reasons]


# ----------------------------------------------------------------------------- bf16
@pytest.fixture(scope="module")
def tiny_batch(tmp_path_factory):
    cfg = tiny_config(tmp_path_factory.mktemp("b"))
    mappo.seed_everything(cfg.seed)
    agent = mappo.make_agent(cfg, torch.device("cpu"))
    envs = trainer.make_vector_env(cfg.env, cfg.n_envs, cfg.seed)
    try:
        roll, next_value, _ = ppo.collect_rollout(agent, envs, cfg, 0, global_step=0)
    finally:
        envs.close()
    adv, ret = ppo.rollout_gae(roll, next_value, cfg)
    return cfg, agent, buffer.make_batch(roll, adv, ret, cfg.chunk_len, torch.device("cpu"))


def test_bf16_update_stays_close_to_fp32(tiny_batch):
    cfg, agent, batch = tiny_batch
    every_env = torch.arange(batch.critic_h0.shape[0])
    with torch.no_grad():
        fp32 = ppo.evaluate_batch(agent, batch, every_env, 4)
        with torch.autocast("cpu", torch.bfloat16):
            bf16 = ppo.evaluate_batch(agent, batch, every_env, 4)
    assert bf16[0].dtype == bf16[2].dtype == torch.float32  # losses are taken in fp32
    assert (bf16[0] - fp32[0]).abs().max() < 0.05  # log-probs
    assert (bf16[2] - fp32[2]).abs().max() < 0.05  # normalised values
    results = {}
    for flag in (False, True):
        a = copy.deepcopy(agent)
        torch.manual_seed(0)
        stats = ppo.ppo_update(a, batch, override(cfg, {"update_bf16": flag}), 4)
        assert all(np.isfinite(v) for v in stats.values())
        results[flag] = torch.cat([p.detach().ravel() for p in a.actor.parameters()])
    start = torch.cat([p.detach().ravel() for p in agent.actor.parameters()])
    assert not torch.equal(results[True], start)
    # bf16 moves the weights about as far as fp32 does, in about the same direction
    step32, step16 = results[False] - start, results[True] - start
    assert torch.nn.functional.cosine_similarity(step32, step16, dim=0) > 0.9


# ----------------------------------------------------------------------------- devices
def test_separate_rollout_networks_train_exactly_like_shared_ones(tmp_path, monkeypatch):
    """Learner and rollout copies on different devices (here cpu and cpu:0, which
    torch treats as different devices) give the same run as one shared copy: the
    plumbing of ``--device cuda`` (rollouts on the CPU), tested without a GPU."""
    shared = tiny_config(tmp_path / "shared")
    mappo.train(shared, progress=False)
    monkeypatch.setattr(agent_module, "ROLLOUT_DEVICE", torch.device("cpu", 0))
    split = tiny_config(tmp_path / "split")
    agent = mappo.make_agent(split, torch.device("cpu"))
    assert agent.rollout_actor is not agent.actor
    assert agent.rollout_value_norm is not agent.value_norm
    mappo.train(split, progress=False)
    a = checkpoint.load_checkpoint(tmp_path / "shared" / "run" / "checkpoint.pt")
    b = checkpoint.load_checkpoint(tmp_path / "split" / "run" / "checkpoint.pt")
    for part in ("actor", "critic", "value_norm"):
        for name, tensor in a[part].items():
            assert torch.equal(tensor, b[part][name]), f"{part}.{name} differs"


@pytest.mark.slow
def test_compiled_update_matches_eager(tiny_batch):
    """``update_compile``: the inductor-compiled replay gives the eager update's weights."""
    cfg, agent, batch = tiny_batch
    results = []
    for flag in (False, True):
        torch._dynamo.reset()
        a = copy.deepcopy(agent)
        c = override(cfg, {"update_compile": flag})
        if flag:
            a.actor_sequence = torch.compile(a.actor.forward_sequence)
            a.critic_sequence = torch.compile(a.critic.forward_sequence)
        torch.manual_seed(0)
        ppo.ppo_update(a, batch, c, 4)
        results.append(torch.cat([p.detach().ravel() for p in a.actor.parameters()]))
    torch.testing.assert_close(results[0], results[1], rtol=1e-3, atol=1e-5)


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_cuda_without_a_gpu_is_a_one_line_error():
    """``diacc train/bench --device cuda`` on a CPU-only machine: one line, exit 2, no traceback."""
    for argv in (
        ["train", "--steps", "2000", "--device", "cuda"],
        ["bench", "--training", "--device", "cuda"],
    ):
        done = subprocess.run(
            [sys.executable, "-m", "diacc.cli", *argv], capture_output=True, text=True, timeout=120
        )
        assert done.returncode == 2, done.stderr
        assert "Traceback" not in done.stderr
        assert "no CUDA device" in done.stderr.strip().splitlines()[-1]


# ----------------------------------------------------------------------------- overlap
def _weights(path):
    payload = checkpoint.load_checkpoint(path)
    return {f"{part}.{k}": v for part in ("actor", "critic") for k, v in payload[part].items()}


def test_overlapped_training_is_reproducible_lagged_and_resumes_exactly(tmp_path, monkeypatch):
    """``overlap``: rollouts beside the update, with the previous update's parameters.

    Same seed, same weights; a run stopped at a checkpoint and resumed equals
    the uninterrupted one (no rollout is prefetched across a checkpoint); and
    it is not the synchronous run (the rollouts act with lagged parameters).
    """
    calls = []
    real = trainer.collect_rollout

    def spy(agent, envs, cfg, update, global_step, sync=True, values=True):
        calls.append((update, sync))
        return real(agent, envs, cfg, update, global_step, sync, values)

    monkeypatch.setattr(trainer, "collect_rollout", spy)
    extra = {"total_steps": 160, "checkpoint_every": 2}  # 4 updates of 40 steps
    runs = {}
    for name, overlap in (("a", True), ("b", True), ("sync", False)):
        calls.clear()
        mappo.train(tiny_config(tmp_path / name, overlap=overlap, **extra), progress=False)
        runs[name] = _weights(tmp_path / name / "run" / "checkpoint.pt")
        if overlap:  # update 1 and 3 prefetched beside updates 0 and 2; 2 follows a checkpoint
            assert calls == [(0, True), (1, False), (2, True), (3, False)]
    split = tiny_config(tmp_path / "split", overlap=True, **extra)
    mappo.train(split, progress=False, stop_after_updates=2)
    mappo.train(split, resume=True, progress=False)
    runs["split"] = _weights(tmp_path / "split" / "run" / "checkpoint.pt")
    for name, tensor in runs["a"].items():
        assert torch.equal(tensor, runs["b"][name]), name
        assert torch.equal(tensor, runs["split"][name]), name
    assert any(not torch.equal(t, runs["sync"][n]) for n, t in runs["a"].items())


# ----------------------------------------------------------------------------- bench
def test_training_bench_rows_and_core_shares(tmp_path):
    """The bench's small learner is configs/small-learner.toml (= the defaults), its paper
    learner configs/paper-learner.toml; every row runs, shares add up."""
    from pathlib import Path

    from diacc.experiments.bench import training
    from diacc.tomlfile import read_toml

    toml = read_toml(Path(__file__).parents[1] / "configs" / "small-learner.toml", ValueError)
    flat = {
        "minibatches": toml["minibatches"],
        **{f"model.{k}": v for k, v in toml["model"].items()},
    }
    assert training.SMALL_LEARNER == flat
    assert override(TrainConfig(), flat) == TrainConfig()
    paper = read_toml(Path(__file__).parents[1] / "configs" / "paper-learner.toml", ValueError)
    assert override(TrainConfig(), paper) == override(TrainConfig(), training.PAPER_LEARNER)
    assert dict(training.LEARNER_ROWS)["paper learner"] == training.PAPER_LEARNER
    labels = [label for label, _, _ in training.configurations("cpu", False, only="learners")]
    assert labels[: len(training.LEARNER_ROWS)] == [label for label, _ in training.LEARNER_ROWS]
    assert "small learner + bf16 + overlap" in labels
    sync = training.core_shares(2.0, 0.5, 1.4, overlap=False)
    assert sync == {"core0": (0.25, 0.7), "core1": (0.0, 0.0)}
    assert training.core_shares(1.0, 0.5, 0.9, overlap=True) == {
        "core0": (0.5, 0.0),
        "core1": (0.0, 0.9),
    }
    # 2 envs x 10 steps are 2 sequences: one minibatch
    tiny = {"overlap": True, "minibatches": 1, **TINY_NETS}
    row = training.measure("diacc", "highway", 2, 2, "cpu", rollout_steps=10, options=tiny)
    assert row["steps_per_s"] > 0 and 0 < row["core1"][1] <= 1.5
    assert row["idle_steps_per_s"] > 0 and row["learner_cpu_s"] > 0


def test_training_bench_names_an_unknown_row(capsys):
    from diacc.experiments.bench import training

    with pytest.raises(ValueError, match="no such row"):
        training.run("cpu", (2,), updates=2, labels=("small learner", "nope"))
    with pytest.raises(SystemExit):
        training.main(["--rows", "small learner,nope"])
    assert "--rows: no such row(s): nope" in capsys.readouterr().err


def test_training_bench_puts_the_learner_devices_side_by_side(capsys, monkeypatch):
    """``--only device``: the CPU path first, then the eager and static updates and the
    env workers on the device (here the CPU too), each with its update time and rate."""
    from diacc.experiments.bench import training

    monkeypatch.setattr(training, "SMALL_LEARNER", {**training.SMALL_LEARNER, **TINY_NETS})
    cuda = [label for label, _, _ in training.configurations("cuda", False, only="device")]
    assert cuda[0] == training.CPU_PATH == "small learner on cpu" and len(cuda) == 4
    assert [label for label, _, _ in training.configurations("cuda", False)][:4] == cuda
    assert training.CPU_PATH not in [r[0] for r in training.configurations("cpu", False)]
    rows = training.run("cpu", (3,), updates=2, rollout_steps=20, only="device")
    paths = [(r["options"].get("update_path"), r["options"]["vector"]) for r in rows]
    assert paths == [
        (None, "batched"),
        ("eager", "batched"),
        ("static", "batched"),
        ("static", "process"),
    ]
    assert all(r["learner_s"] > 0 and r["steps_per_s"] > 0 for r in rows)
    out = capsys.readouterr().out
    assert "small learner on cpu: static update over small learner on cpu: x" in out
    # benchmarks/speed/gpu_host.sh names the compiled row by its label
    script = (Path(__file__).parents[1] / "benchmarks/speed/gpu_host.sh").read_text()
    label = script.split('--rows "')[1].split('"')[0]
    assert training.select_rows(training.configurations("cuda", True, only="device"), (label,))
