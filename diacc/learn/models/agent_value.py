"""Per-agent values (``TrainConfig.critic_values = "per_agent"``): credit assignment.

The paper's critic gives one value per environment and every CAV shares the
team advantage, so an agent whose action helped and one whose action hurt get
the same signal (measured: policy KL 0.000-0.004 per update at 50k steps).
MAPPO's agent-specific global state answers this by valuing each agent with
its own features beside the global ones: here the team critic's recurrent
embedding of the global state (its encoder and GRU, unchanged) is joined with
each CAV slot's own features (its actor ``self_state`` and whether it is on
the road), and a small head gives one value per slot. GAE then runs per agent
on the shared team reward.

CAVs off the road keep a value (their features are zero and the alive flag is
0, MAPPO's death masking): their target is still the team's return, so a
slot's value stays defined after its CAV leaves and the bootstrap of the
steps before it leaves is not a guess.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor, nn

from diacc.config import ModelConfig
from diacc.envs.observation import SELF_FEATURES
from diacc.learn.models.inputs import TensorDict, require
from diacc.learn.models.layers import VALUE_GAIN, mlp, orthogonal_init
from diacc.learn.models.recurrent import RecurrentNet

#: Key of the per-slot features in the critic's input: (..., C, AGENT_FEATURES).
AGENT_KEY = "agent_self"
#: The actor's self features and the alive flag.
AGENT_FEATURES = SELF_FEATURES + 1


def agent_features(self_state: np.ndarray, alive: np.ndarray) -> np.ndarray:
    """(..., C, AGENT_FEATURES) float32 features of each CAV slot (zero when off the road)."""
    on_road = np.asarray(alive, np.float32)[..., None]  # (..., C, 1)
    return np.concatenate([self_state, on_road], axis=-1).astype(np.float32)


class AgentValueCritic(nn.Module):
    """Team critic's embedding + each slot's own features -> one value per CAV slot.

    ``critic(state (B, ...) with AGENT_KEY (B, C, F), hidden (B, H), start (B,))
    -> (values (B, C), hidden)``; ``forward_sequence`` as
    :meth:`RecurrentNet.forward_sequence` with values (T, B, C). The team
    critic's own value head is not used.
    """

    def __init__(self, team: RecurrentNet, cfg: ModelConfig) -> None:
        super().__init__()
        self.team = team
        hidden = cfg.hidden_dim
        self.agent_embed = mlp(AGENT_FEATURES, hidden, hidden, cfg.leaky_slope)
        self.value_head = nn.Sequential(
            nn.Linear(team.hidden_size + hidden, hidden), nn.LeakyReLU(cfg.leaky_slope)
        )
        self.value_out = nn.Linear(hidden, 1)
        orthogonal_init(self.agent_embed)
        orthogonal_init(self.value_head)
        nn.init.orthogonal_(self.value_out.weight, gain=VALUE_GAIN)
        nn.init.zeros_(self.value_out.bias)

    @property
    def hidden_size(self) -> int:
        return self.team.hidden_size

    def _values(self, embedding: Tensor, agents: Tensor) -> Tensor:
        """embedding (..., H), agents (..., C, F) -> values (..., C)."""
        per_agent = self.agent_embed(agents)  # (..., C, hidden)
        shared = embedding[..., None, :].expand(*per_agent.shape[:-1], embedding.shape[-1])
        joined = torch.cat([shared, per_agent], dim=-1)  # (..., C, H + hidden)
        return self.value_out(self.value_head(joined)).squeeze(-1)

    def forward(
        self, inputs: TensorDict, hidden: Tensor, episode_start: Tensor
    ) -> tuple[Tensor, Tensor]:
        require(inputs, (AGENT_KEY,), tuple(hidden.shape[:1]), type(self).__name__)
        _, new_hidden = self.team(inputs, hidden, episode_start)  # (B, H)
        return self._values(new_hidden, inputs[AGENT_KEY]), new_hidden

    def forward_sequence(
        self, inputs: TensorDict, hidden: Tensor, episode_starts: Tensor, all_states: bool = False
    ) -> tuple[Tensor, Tensor]:
        require(inputs, (AGENT_KEY,), tuple(episode_starts.shape), "AgentValue")
        states = self.team.hidden_states(inputs, hidden, episode_starts)  # (T, B, H)
        return self._values(states, inputs[AGENT_KEY]), (states if all_states else states[-1])
