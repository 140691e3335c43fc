"""The one acting step (:mod:`diacc.learn.acting`): greedy, the two sampled draws, PSAR's
action mask, and the training, evaluation and ``load_policy`` paths that all go through it."""

from __future__ import annotations

import torch
from test_mappo import rollout_batch, tiny_config

import diacc
from diacc.envs.action_mask import masked_logits
from diacc.envs.spaces import actor_obs_from_rows
from diacc.experiments.policies import CheckpointPolicy
from diacc.learn import acting, ppo

CHECKPOINT = "checkpoints/diacc-train50-paper-congestion-s1.pt"
#: (B, 5) logits of 3 CAVs; the mask forbids each CAV's most likely action
LOGITS = torch.tensor(
    [[0.0, 3.0, 1.0, 1.0, 0.5], [2.0, 0.0, 0.0, 1.5, -1.0], [0.0, 0.0, 0.0, 0.0, 9.0]]
)
MASK = torch.tensor(
    [[True, False, True, True, True], [False, True, True, True, True], [True] * 4 + [False]]
)


class FixedActor(torch.nn.Module):
    """An actor whose logits are :data:`LOGITS` whatever it sees; its hidden state counts
    steps, restarting at 1 where ``start``."""

    def forward(self, obs, hidden, start):
        return LOGITS, hidden * (~start)[:, None] + 1


def _decide(mask: torch.Tensor, **mode) -> acting.Decision:
    hidden = torch.full((3, 2), 4.0)  # (B, H)
    start = torch.tensor([False, True, False])
    return acting.decide(FixedActor(), {"action_mask": mask}, hidden, start, **mode)


def test_greedy_takes_the_most_likely_allowed_action_and_steps_the_memory():
    everything = torch.ones(3, 5, dtype=torch.bool)
    assert _decide(everything).action.tolist() == [1, 0, 4]
    masked = _decide(MASK)
    assert masked.action.tolist() == masked.greedy.tolist() == [2, 3, 0]  # first of ties
    assert masked.hidden[:, 0].tolist() == [5.0, 1.0, 5.0]


def test_no_draw_picks_a_masked_action_and_each_keeps_its_random_stream():
    generator = torch.Generator().manual_seed(3)
    seeded = [_decide(MASK, sampled=True, generator=generator).action for _ in range(200)]
    torch.manual_seed(3)
    global_rng = [_decide(MASK, sampled=True).action for _ in range(200)]
    for actions in (torch.stack(seeded), torch.stack(global_rng)):  # (200, 3)
        assert MASK[torch.arange(3), actions].all()
        assert len(set(actions[:, 0].tolist())) > 1  # sampled, not greedy
    # evaluation: multinomial on the softmax, from the episode's generator
    generator.manual_seed(7)
    reference = torch.Generator().manual_seed(7)
    probs = torch.softmax(masked_logits(LOGITS, MASK), -1)
    drawn = _decide(MASK, sampled=True, generator=generator).action
    assert drawn.equal(torch.multinomial(probs, 1, generator=reference)[:, 0])
    # training: Categorical.sample on torch's global RNG
    torch.manual_seed(7)
    drawn = _decide(MASK, sampled=True)
    torch.manual_seed(7)
    assert drawn.action.equal(drawn.policy.sample())
    assert (drawn.policy.log_prob(torch.tensor([1, 0, 4])).exp() == 0).all()


def test_training_evaluation_and_load_policy_act_through_decide(tmp_path, monkeypatch):
    calls: list[tuple[bool, bool]] = []  # (sampled, with a generator) of each call

    def spy(actor, obs, hidden, start, sampled=False, generator=None):
        calls.append((sampled, generator is not None))
        return decide(actor, obs, hidden, start, sampled, generator)

    decide = acting.decide
    monkeypatch.setattr(acting, "decide", spy)  # evaluation and load_policy import it on call
    monkeypatch.setattr(ppo, "decide", spy)
    cfg = tiny_config(tmp_path)
    rollout_batch(cfg)
    assert calls == [(True, False)] * cfg.rollout_steps
    calls.clear()
    policy = diacc.load_policy(CHECKPOINT, sampled=True)
    env = policy.make_env()
    try:
        observations, _ = env.reset(seed=0)
        policy.act(observations)
    finally:
        env.close()
    assert calls == [(True, True)]
    calls.clear()
    evaluator = CheckpointPolicy(CHECKPOINT)
    evaluator.begin_episode(len(observations), seed=0)
    evaluator.act(actor_obs_from_rows(policy.spec, list(observations.values())), True)
    assert calls == [(False, True)]
