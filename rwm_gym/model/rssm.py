"""Recurrent state-space model (Dreamer-style) baseline: a deterministic GRU path plus a stochastic Gaussian latent.

Per step: h' = GRU(h, [state, action, z]); the prior p(z' | h') is a diagonal Gaussian; when the true next state is
known (the history during warm-up) z' is drawn from the posterior q(z' | h', next state) and the KL(q || p) is
reported for the loss, otherwise from the prior. In eval mode the means replace the samples, so evaluation is
deterministic. The heads read [h', z'].
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn
from torch.distributions import Normal, kl_divergence

from rwm_gym.model.base import Hidden, WorldModel
from rwm_gym.model.config import ModelConfig
from rwm_gym.model.heads import Heads
from rwm_gym.model.prediction import Prediction

_MIN_STD = 0.1


def _gaussian(net: nn.Module, x: torch.Tensor) -> Normal:
    mean, raw_std = net(x).chunk(2, dim=-1)
    return Normal(mean, F.softplus(raw_std) + _MIN_STD)


class RSSM(WorldModel):
    """Hidden = (deterministic h (B, hidden_size), latent z (B, rssm_latent))."""

    filters_with_next_state = True

    def __init__(self, config: ModelConfig) -> None:
        super().__init__(config)
        h, z, s = config.hidden_size, config.rssm_latent, config.state_dim
        self.inputs = nn.Sequential(nn.Linear(s + config.action_dim + z, h), nn.ELU())
        self.cell = nn.GRUCell(h, h)
        self.prior = nn.Sequential(nn.Linear(h, config.head_hidden), nn.ELU(), nn.Linear(config.head_hidden, 2 * z))
        self.posterior = nn.Sequential(
            nn.Linear(h + s, config.head_hidden), nn.ELU(), nn.Linear(config.head_hidden, 2 * z)
        )
        self.heads = Heads(h + z, h + z, config)

    def initial_hidden(self, batch_size: int, device: torch.device | str | None = None) -> Hidden:
        device = self.device if device is None else device
        return (
            torch.zeros(batch_size, self.config.hidden_size, device=device),
            torch.zeros(batch_size, self.config.rssm_latent, device=device),
        )

    def step(
        self,
        hidden: Hidden,
        state: torch.Tensor,
        action: torch.Tensor,
        member: torch.Tensor | None = None,
        next_state: torch.Tensor | None = None,
    ) -> tuple[Hidden, Prediction]:
        h, z = hidden
        h = self.cell(self.inputs(torch.cat([state, action, z], dim=-1)), h)
        prior = _gaussian(self.prior, h)
        kl = None
        if next_state is not None:
            posterior = _gaussian(self.posterior, torch.cat([h, next_state], dim=-1))
            z = posterior.rsample() if self.training else posterior.mean
            kl = kl_divergence(posterior, prior).sum(dim=-1)
        else:
            z = prior.rsample() if self.training else prior.mean
        features = torch.cat([h, z], dim=-1)
        prediction = self.heads(features, features, state, member)
        prediction.kl = kl
        return (h, z), prediction
