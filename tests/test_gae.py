"""GAE against hand-computed numbers, with a termination and a truncation mid-rollout."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from diacc.learn.buffer import compute_gae
from diacc.learn.valuenorm import ValueNorm

REWARDS = np.array([[1.0], [2.0], [3.0]])
VALUES = np.array([[0.5], [0.4], [0.3]])
NEXT = np.array([0.2])
NONE = np.zeros((3, 1), bool)


def test_gae_with_termination_in_the_middle():
    terminated = NONE.copy()
    terminated[1] = True
    adv, ret = compute_gae(REWARDS, VALUES, NEXT, terminated, NONE, np.zeros((3, 1)), 0.9, 0.8)
    # t=2: 3 + .9*.2 - .3 = 2.88 ; t=1: 2 - .4 = 1.6 (no future) ; t=0: 1 + .9*.4 - .5 + .72*1.6
    assert adv[:, 0] == pytest.approx([0.86 + 0.72 * 1.6, 1.6, 2.88])
    assert ret[:, 0] == pytest.approx(adv[:, 0] + VALUES[:, 0])


def test_gae_bootstraps_truncation_from_the_final_state():
    truncated = NONE.copy()
    truncated[1] = True
    final = np.array([[0.0], [1.0], [0.0]])
    adv, _ = compute_gae(REWARDS, VALUES, NEXT, NONE, truncated, final, 0.9, 0.8)
    # t=1: 2 + .9*1.0 - .4 = 2.5 and the trace does not carry into t=2's episode.
    assert adv[:, 0] == pytest.approx([0.86 + 0.72 * 2.5, 2.5, 2.88])


def test_gae_without_episode_end_is_discounted_td_lambda():
    adv, _ = compute_gae(REWARDS, VALUES, NEXT, NONE, NONE, np.zeros((3, 1)), 1.0, 1.0)
    # gamma = lambda = 1: advantage = sum of future rewards + V(next) - V(s_t)
    assert adv[:, 0] == pytest.approx([6.2 - 0.5, 5.2 - 0.4, 3.2 - 0.3])


def test_value_norm_round_trip_and_scale():
    norm = ValueNorm(beta=0.9)
    data = torch.tensor([100.0, 110.0, 90.0, 105.0])
    for _ in range(200):
        norm.update(data)
    z = norm.normalize(data)
    assert abs(float(z.mean())) < 0.1 and 0.5 < float(z.std()) < 1.5
    assert torch.allclose(norm.denormalize(z), data, atol=1e-3)
