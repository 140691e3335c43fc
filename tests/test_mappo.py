"""Recurrent MAPPO: chunked replay, death masking, checkpoints and exact resume."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from helpers import SHORT_MAP

from diacc.config import TrainConfig, override
from diacc.envs.vector import make_vector_env
from diacc.learn.agent import make_agent
from diacc.learn.buffer import make_batch
from diacc.learn.checkpoint import CheckpointError, config_from_checkpoint, load_checkpoint
from diacc.learn.mappo import seed_everything, train
from diacc.learn.ppo import collect_rollout, evaluate_batch, ppo_update, rollout_gae
from diacc.sim.scenario import Scenario

TINY = {
    "n_envs": 2,
    "rollout_steps": 20,
    "chunk_len": 10,
    "total_steps": 80,
    "device": "cpu",
    "epochs": 2,
    "env.sim.episode_steps": 15,
    "model.hidden_dim": 32,
    "model.gru_hidden": 32,
    "model.cross_dim": 32,
}


def tiny_config(tmp_path, **extra) -> TrainConfig:
    """Two envs of 8 vehicles on a 160 m road: CAVs leave within an episode."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    road = tmp_path / "short.toml"
    road.write_text(SHORT_MAP)
    cfg = override(
        TrainConfig(), {**TINY, "run_dir": str(tmp_path / "run"), "env.map": str(road), **extra}
    )
    return override(cfg, {"env.scenario": Scenario(n_vehicles=8, cav_penetration=0.5)})


def rollout_batch(cfg: TrainConfig):
    """A fresh seeded agent, one rollout of it and the batch made of it."""
    seed_everything(cfg.seed)
    agent = make_agent(cfg, torch.device("cpu"))
    envs = make_vector_env(cfg.env, cfg.n_envs, cfg.seed)
    try:
        roll, next_value, stats = collect_rollout(agent, envs, cfg, 0, global_step=0)
    finally:
        envs.close()
    adv, ret = rollout_gae(roll, next_value, cfg)
    return agent, roll, make_batch(roll, adv, ret, cfg.chunk_len, torch.device("cpu"))


@pytest.fixture(scope="module")
def rollout_and_batch(tmp_path_factory):
    cfg = tiny_config(tmp_path_factory.mktemp("r"))
    return (cfg, *rollout_batch(cfg))


def test_rollout_has_episode_boundaries_and_dead_cavs(rollout_and_batch):
    _, _, roll, _ = rollout_and_batch
    # 20 steps with 15-step episodes: every env starts at least twice.
    assert roll.episode_start[0].all() and (roll.episode_start.sum(axis=0) >= 2).all()
    assert (roll.terminated | roll.truncated).any()
    assert roll.alive.any()


def test_chunked_replay_reproduces_rollout_logprobs(rollout_and_batch):
    cfg, agent, _, batch = rollout_and_batch
    with torch.no_grad():
        every_env = torch.arange(batch.critic_h0.shape[0])
        logprob, _, _, agents = evaluate_batch(agent, batch, every_env, 4)
    # On the road; a replay need not encode CAVs off it (recurrent.needed_rows).
    alive = batch.alive[:, agents].bool()
    ratio = (logprob - batch.logprobs[:, agents]).exp()[alive]
    assert torch.allclose(ratio, torch.ones_like(ratio), atol=1e-5)


def test_value_clipping_keeps_every_value_gradient_in_the_first_pass(rollout_and_batch):
    """The clip centre is the critic's own rollout output, so before any parameter
    step no critic sample can be clipped away (re-normalising de-normalised values
    with freshly updated statistics zeroed most value gradients)."""
    cfg, agent, _, batch = rollout_and_batch
    cfg = override(cfg, {"epochs": 1, "minibatches": 1})
    a = copy.deepcopy(agent)
    grads = []
    replay = a.critic.forward_sequence

    def recording(*args, **kwargs):
        values, hidden = replay(*args, **kwargs)
        values.register_hook(lambda g: grads.append(g.detach().clone()))
        return values, hidden

    a.critic.forward_sequence = recording
    ppo_update(a, batch, cfg, 4)
    assert len(grads) == 1
    assert (grads[0] != 0).float().mean().item() > 0.99


def test_dead_steps_contribute_nothing(rollout_and_batch):
    cfg, agent, _, batch = rollout_and_batch
    cfg = override(cfg, {"epochs": 1})
    dead = batch.alive == 0
    assert dead.any(), "the tiny rollout should contain dead CAV steps"
    garbage = copy.copy(batch)
    garbage.advantages = torch.where(dead, torch.full_like(batch.advantages, 1e3), batch.advantages)
    garbage.actions = torch.where(dead, (batch.actions + 1) % 5, batch.actions)
    garbage.logprobs = torch.where(dead, batch.logprobs - 3.0, batch.logprobs)
    results = []
    for b in (batch, garbage):
        a = copy.deepcopy(agent)
        torch.manual_seed(0)
        ppo_update(a, b, cfg, 4)
        results.append(torch.cat([p.detach().ravel() for p in a.actor.parameters()]))
    assert torch.equal(results[0], results[1])


def _rollout_at(cfg: TrainConfig, global_step: int):
    """One seeded rollout of a fresh agent at training step ``global_step``."""
    seed_everything(cfg.seed)
    agent = make_agent(cfg, torch.device("cpu"))
    envs = make_vector_env(cfg.env, cfg.n_envs, cfg.seed)
    try:
        return collect_rollout(agent, envs, cfg, 0, global_step)
    finally:
        envs.close()


def test_the_training_step_sets_the_temperature_of_the_rollouts_rewards(tmp_path):
    """Same seed, the start and the end of the schedule (tau 2 and 0.05): the same
    transitions, other team rewards; the episode returns sum the envs' team rewards."""
    cfg = tiny_config(tmp_path)
    hot, _, hot_stats = _rollout_at(cfg, 0)
    cold, _, cold_stats = _rollout_at(cfg, cfg.total_steps)
    assert (hot_stats.tau, cold_stats.tau) == pytest.approx((2.0, 0.05))
    np.testing.assert_array_equal(hot.actions, cold.actions)
    np.testing.assert_array_equal(hot.alive, cold.alive)
    assert not np.array_equal(hot.rewards, cold.rewards)
    assert (cold.rewards <= hot.rewards + 1e-12).all()  # the softmin leans to the worst CAV
    assert hot_stats.reward_terms["tau"] == [2.0] * cfg.rollout_steps
    assert cold_stats.reward_terms["tau"] == [cold_stats.tau] * cfg.rollout_steps
    assert hot_stats.reward_terms["global"] == cold_stats.reward_terms["global"]
    for roll, stats in ((hot, hot_stats), (cold, cold_stats)):
        acc, returns = np.zeros(cfg.n_envs), []
        for t in range(cfg.rollout_steps):
            acc += roll.rewards[t]
            for e in np.flatnonzero(roll.terminated[t] | roll.truncated[t]):
                returns.append(float(acc[e]))
                acc[e] = 0.0
        assert len(stats.episodes) >= cfg.n_envs
        assert [ep["return"] for ep in stats.episodes] == returns
        assert list(stats.episodes[0])[:2] == ["return", "length"]  # progress.jsonl's order


def test_training_anneals_the_envs_temperature_rollout_by_rollout(tmp_path, monkeypatch):
    """The trainer gives each rollout its global step; the envs' team rewards are made at
    the schedule's temperature there, constant within the rollout."""
    from diacc.learn import trainer

    cfg = tiny_config(tmp_path, **{"env.reward.tau_anneal_fraction": 0.5})
    taus, real = [], trainer.collect_rollout

    def spy(agent, envs, cfg, update, global_step, **options):
        out = real(agent, envs, cfg, update, global_step, **options)
        taus.append(envs.tau)  # set by the trainer for the rollout: the envs count nothing
        return out

    monkeypatch.setattr(trainer, "collect_rollout", spy)
    train(cfg, progress=False)
    assert taus == pytest.approx([2.0, 0.05])  # 40 of 80 steps: the schedule ends after one
    import json

    rows = [json.loads(line) for line in (tmp_path / "run" / "progress.jsonl").open()]
    assert [row["tau"] for row in rows] == taus
    assert [row["reward/tau"] for row in rows] == pytest.approx(taus)


def test_resume_matches_uninterrupted_run(tmp_path):
    straight = tiny_config(tmp_path / "a")
    train(straight, progress=False)
    split = tiny_config(tmp_path / "b")
    train(split, progress=False, stop_after_updates=1)
    train(split, resume=True, progress=False)
    a = load_checkpoint(tmp_path / "a" / "run" / "checkpoint.pt")
    b = load_checkpoint(tmp_path / "b" / "run" / "checkpoint.pt")
    assert a["update"] == b["update"] == 2
    for part in ("actor", "critic"):
        for name, tensor in a[part].items():
            assert torch.allclose(tensor, b[part][name], atol=1e-6), f"{part}.{name} differs"
    logs = [(tmp_path / d / "run" / "progress.jsonl").read_text().splitlines() for d in ("a", "b")]
    import json

    last = [json.loads(lines[-1]) for lines in logs]
    assert last[0]["policy_loss"] == pytest.approx(last[1]["policy_loss"], rel=1e-5, abs=1e-7)


def test_stop_at_step_ends_at_the_update_reaching_it_on_the_full_schedule(tmp_path):
    """``--stop-at``: equal steps of one schedule (tau and lr follow ``total_steps``)."""
    cfg = tiny_config(tmp_path)  # 2 updates of 40 steps
    train(cfg, progress=False, stop_at_step=40)
    assert load_checkpoint(tmp_path / "run" / "checkpoint.pt")["global_step"] == 40
    train(cfg, resume=True, progress=False, stop_at_step=40)  # already there: nothing to do
    assert load_checkpoint(tmp_path / "run" / "checkpoint.pt")["global_step"] == 40
    train(cfg, resume=True, progress=False, stop_at_step=41)
    payload = load_checkpoint(tmp_path / "run" / "checkpoint.pt")
    assert payload["global_step"] == 80 and payload["config"]["total_steps"] == 80


def test_training_on_two_maps_resumes_exactly_and_differs_from_one(tmp_path):
    """extra_maps: env 1 drives a second road (lanes dropping on the right); a
    split run resumes to the same weights, and the second map changes training."""
    right = tmp_path / "right.toml"
    right.write_text(
        SHORT_MAP.replace('name = "short"', 'name = "short-right"\ndrop_side = "right"')
    )
    runs = {}
    for name, stop in (("a", None), ("b", 1)):
        cfg = tiny_config(tmp_path / name, extra_maps=(str(right),))
        train(cfg, progress=False, stop_after_updates=stop)
        if stop:
            train(cfg, resume=True, progress=False)
        runs[name] = load_checkpoint(tmp_path / name / "run" / "checkpoint.pt")
    one_map = tiny_config(tmp_path / "c")
    train(one_map, progress=False)
    runs["c"] = load_checkpoint(tmp_path / "c" / "run" / "checkpoint.pt")
    assert config_from_checkpoint(runs["a"]).extra_maps == (str(right),)
    for name, tensor in runs["a"]["actor"].items():
        assert torch.allclose(tensor, runs["b"]["actor"][name], atol=1e-6), name
    assert any(
        not torch.equal(tensor, runs["c"]["actor"][name])
        for name, tensor in runs["a"]["actor"].items()
    )


def test_init_from_starts_from_a_checkpoints_networks_with_a_fresh_optimiser(tmp_path):
    """Fine-tuning: the networks and value normaliser come from the checkpoint, the
    optimiser and the step count start afresh; a checkpoint of other sizes or another
    variant, or a missing one, is a one-line error."""
    from diacc.config import ConfigError, validate
    from diacc.learn.checkpoint import init_networks

    source = tiny_config(tmp_path / "a", total_steps=40)
    train(source, progress=False)
    path = tmp_path / "a" / "run" / "checkpoint.pt"
    saved = load_checkpoint(path)
    tuned = tiny_config(tmp_path / "b", total_steps=40, init_from=str(path), seed=7)
    agent = make_agent(tuned, torch.device("cpu"))
    origin = init_networks(agent, path, tuned)
    assert origin["global_step"] == 40 and origin["variant"] == "diacc"
    for name, tensor in agent.actor.state_dict().items():
        assert torch.equal(tensor, saved["actor"][name]), name
    assert not agent.optimizer.state_dict()["state"]
    train(tuned, progress=False)
    after = load_checkpoint(tmp_path / "b" / "run" / "checkpoint.pt")
    assert after["global_step"] == 40 and after["update"] == 1
    assert "networks from" in (tmp_path / "b" / "run" / "train.log").read_text()
    fresh = tiny_config(tmp_path / "c", total_steps=40, seed=7)
    train(fresh, progress=False)
    scratch = load_checkpoint(tmp_path / "c" / "run" / "checkpoint.pt")
    # One update moves the weights a little: the tuned run stays near its source.
    name = next(iter(saved["actor"]))
    to_source = (after["actor"][name] - saved["actor"][name]).abs().max()
    to_scratch = (after["actor"][name] - scratch["actor"][name]).abs().max()
    assert to_source < to_scratch

    wider = tiny_config(tmp_path / "d", init_from=str(path), **{"model.hidden_dim": 16})
    with pytest.raises(CheckpointError, match=r"other model\.\* sizes"):
        init_networks(make_agent(wider, torch.device("cpu")), path, wider)
    with pytest.raises(CheckpointError, match="variant 'diacc', not 'mappo-iadm'"):
        other = override(tuned, {"variant": "mappo-iadm"})
        init_networks(make_agent(other, torch.device("cpu")), path, other)
    with pytest.raises(ConfigError, match="does not exist"):
        validate(override(tuned, {"init_from": str(tmp_path / "missing.pt")}))


def test_bad_checkpoints_give_one_line_errors(tmp_path):
    cfg = tiny_config(tmp_path, total_steps=40)
    train(cfg, progress=False)
    path = tmp_path / "run" / "checkpoint.pt"
    payload = torch.load(path, weights_only=True)

    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(path.read_bytes()[:100])
    with pytest.raises(CheckpointError, match="is corrupt"):
        load_checkpoint(corrupt)

    poisoned = copy.deepcopy(payload)
    name = next(iter(poisoned["actor"]))
    poisoned["actor"][name] = poisoned["actor"][name].float() * np.nan
    torch.save(poisoned, tmp_path / "nan.pt")
    with pytest.raises(CheckpointError, match="NaN"):
        load_checkpoint(tmp_path / "nan.pt")

    with pytest.raises(CheckpointError, match="variant 'diacc', not 'mappo'"):
        train(override(cfg, {"variant": "mappo"}), resume=True, progress=False)
    with pytest.raises(CheckpointError, match="does not exist"):
        load_checkpoint(tmp_path / "missing.pt")


@pytest.mark.parametrize("critic_values", ["team", "per_agent"])
def test_values_after_the_rollout_equal_values_stepped_with_the_envs(tmp_path, critic_values):
    """rollout_values (one pass per chunk, after the loop) gives the values, hidden states,
    truncation bootstraps and V(s_S) of the critic stepped along with the envs."""
    from diacc.envs.observation import ActorObs, CriticState
    from diacc.learn.ppo import critic_inputs

    cfg = tiny_config(tmp_path, critic_values=critic_values)
    agent, roll, _ = rollout_batch(cfg)
    per_agent = critic_values == "per_agent"
    critic, norm = agent.critic, agent.value_norm
    assert roll.truncated.any() and roll.cut_states, "test needs an episode cut by the limit"
    hidden = torch.zeros(cfg.n_envs, critic.hidden_size)
    with torch.no_grad():
        for t in range(cfg.rollout_steps):
            np.testing.assert_allclose(roll.critic_hidden[t], hidden.numpy(), atol=1e-5)
            inputs = critic_inputs(roll.critic_state[t], roll.actor_obs[t], per_agent, "cpu")
            value, hidden = critic(inputs, hidden, torch.as_tensor(roll.episode_start[t]))
            np.testing.assert_allclose(roll.values_normalised[t], value.numpy(), atol=1e-5)
            np.testing.assert_allclose(roll.values[t], norm.denormalize(value).numpy(), atol=1e-5)
            for cut_t, e, final_state, final_actor in roll.cut_states:
                if cut_t == t:
                    v, _ = critic(
                        critic_inputs(
                            CriticState.stack([final_state]),
                            ActorObs.stack([final_actor]),
                            per_agent,
                            "cpu",
                        ),
                        hidden[e : e + 1],
                        torch.zeros(1, dtype=torch.bool),
                    )
                    want = norm.denormalize(v).numpy()[0]
                    np.testing.assert_allclose(roll.final_values[t, e], want, atol=1e-5)
    assert not np.all(roll.values == 0)


def test_proximal_policy_of_an_unlagged_rollout_is_the_behaviour_policy(rollout_and_batch):
    """add_proximal_policy replays the actor: on a rollout the same parameters collected,
    its log-probs are the stored ones and every behaviour weight is 1."""
    from diacc.learn.ppo import add_proximal_policy

    cfg, agent, roll, batch = rollout_and_batch
    lagged = copy.copy(batch)
    add_proximal_policy(agent, lagged, cfg, roll.actions.shape[2])
    alive = batch.alive.bool()
    torch.testing.assert_close(
        lagged.prox_logprobs[alive], batch.logprobs[alive], rtol=0, atol=1e-5
    )
    weights = lagged.behaviour_weights[alive]
    torch.testing.assert_close(weights, torch.ones_like(weights), rtol=0, atol=1e-4)
    assert batch.prox_logprobs is None


def test_training_checks_for_a_collapsed_greedy_policy_at_every_checkpoint(tmp_path, monkeypatch):
    """Issue 58: the rollout counts the actor's argmax on every living CAV's decision,
    ``progress.jsonl`` records the top action's share, and the run log says at each
    checkpoint whether the greedy policy collapsed (an untouched actor, then one made to
    prefer one action everywhere)."""
    import json

    from diacc.learn import ppo

    cfg = tiny_config(tmp_path / "ok", checkpoint_every=1)
    train(cfg, progress=False)
    log = (tmp_path / "ok" / "run" / "train.log").read_text()
    # under 200 decisions per check: a share, never a verdict
    assert log.count("collapse check, updates ") == 2 and "collapsed policy" not in log
    rows = [json.loads(line) for line in (tmp_path / "ok" / "run" / "progress.jsonl").open()]
    assert all(0.2 <= row["greedy_top_share"] <= 1.0 for row in rows)

    real = ppo.collect_rollout

    def biased(agent, *args, **kwargs):  # the actor's last layer prefers 'right' (2)
        with torch.no_grad():
            last = [m for m in agent.actor.modules() if isinstance(m, torch.nn.Linear)][-1]
            last.bias[2] = 1e3
        agent.sync_rollout()
        return real(agent, *args, **{**kwargs, "sync": False})

    from diacc.learn import trainer

    monkeypatch.setattr(trainer, "collect_rollout", biased)
    cfg = tiny_config(tmp_path / "bad", checkpoint_every=2)
    train(cfg, progress=False)
    log = (tmp_path / "bad" / "run" / "train.log").read_text()
    assert "the actor's greedy policy picked 'right' on 100.0%" in log
    assert "in updates 1-2 of training: a collapsed policy" in log
