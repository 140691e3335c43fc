"""Value normalisation (MAPPO practice): the critic predicts normalised returns.

Returns change scale by orders of magnitude while a policy improves (the exit
bonus alone is 20 per CAV). Regressing the critic onto returns standardised by
a slowly moving, debiased mean and variance keeps the value loss well
conditioned; values are de-normalised before GAE.
"""

from __future__ import annotations

import torch
from torch import nn


class ValueNorm(nn.Module):
    """Running mean/variance with exponential decay ``beta`` and debiasing."""

    def __init__(self, beta: float = 0.99999, epsilon: float = 1e-5) -> None:
        super().__init__()
        self.beta, self.epsilon = beta, epsilon
        self.register_buffer("running_mean", torch.zeros((), dtype=torch.float64))
        self.register_buffer("running_mean_sq", torch.zeros((), dtype=torch.float64))
        self.register_buffer("debiasing_term", torch.zeros((), dtype=torch.float64))

    def _mean_var(self) -> tuple[torch.Tensor, torch.Tensor]:
        debias = self.debiasing_term.clamp(min=self.epsilon)
        mean = self.running_mean / debias
        var = (self.running_mean_sq / debias - mean**2).clamp(min=1e-2)
        return mean, var

    @torch.no_grad()
    def update(self, values: torch.Tensor) -> None:
        """Fold a batch of (unnormalised) returns into the running statistics."""
        values = values.detach().to(torch.float64).reshape(-1)
        self.running_mean.mul_(self.beta).add_(values.mean() * (1 - self.beta))
        self.running_mean_sq.mul_(self.beta).add_((values**2).mean() * (1 - self.beta))
        self.debiasing_term.mul_(self.beta).add_(1 - self.beta)

    def normalize(self, values: torch.Tensor) -> torch.Tensor:
        mean, var = self._mean_var()
        return ((values - mean) / var.sqrt()).to(values.dtype)

    def denormalize(self, values: torch.Tensor) -> torch.Tensor:
        mean, var = self._mean_var()
        return (values * var.sqrt() + mean).to(values.dtype)
