"""Baseline world models under the RWM interface: an MLP over a short stacked history, a causal Transformer over a
bounded window, and "the state stays the same". The RSSM lives in `rssm.py`.

Their hidden state is the history they condition on, so the imagined env can reset and warm them up exactly like
the RWM.
"""

from __future__ import annotations

import torch
from torch import nn

from rwm_gym.model.base import Hidden, WorldModel
from rwm_gym.model.config import ModelConfig
from rwm_gym.model.heads import Heads
from rwm_gym.model.prediction import Prediction


def _push(buffer: torch.Tensor, token: torch.Tensor) -> torch.Tensor:
    """Drop the oldest entry of (B, K, ...) and append token (B, ...) as the newest (last) one."""
    return torch.cat([buffer[:, 1:], token.unsqueeze(1)], dim=1)


class MLPModel(WorldModel):
    """One-step MLP over the last `mlp_history` (state, action) pairs, flattened.

    Hidden = (history (B, K, S + A),), oldest first, zeros before the first steps.
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__(config)
        width, layers = config.hidden_size, []
        inputs = config.mlp_history * (config.state_dim + config.action_dim)
        for _ in range(config.num_layers):
            layers += [nn.Linear(inputs, width), nn.ELU()]
            inputs = width
        self.trunk = nn.Sequential(*layers)
        self.heads = Heads(width, width, config)

    def initial_hidden(self, batch_size: int, device: torch.device | str | None = None) -> Hidden:
        c = self.config
        shape = (batch_size, c.mlp_history, c.state_dim + c.action_dim)
        return (torch.zeros(shape, device=self.device if device is None else device),)

    def step(self, hidden: Hidden, state: torch.Tensor, action: torch.Tensor, member: torch.Tensor | None = None,
             next_state: torch.Tensor | None = None) -> tuple[Hidden, Prediction]:
        history = _push(hidden[0], torch.cat([state, action], dim=-1))
        features = self.trunk(history.flatten(1))
        return (history,), self.heads(features, features, state, member)


class TransformerModel(WorldModel):
    """Transformer encoder over the last `transformer_context` (state, action) tokens; reads out the newest one.

    Hidden = (tokens (B, T, S + A), valid (B, T) bool), oldest first. The window holds only past and present tokens,
    so attending over all of it is causal; empty slots before the first steps are masked out. Positions are learned
    per slot, counted back from the newest token.
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__(config)
        d = config.transformer_dim
        self.embed = nn.Linear(config.state_dim + config.action_dim, d)
        self.position = nn.Parameter(torch.randn(config.transformer_context, d) * 0.02)
        layer = nn.TransformerEncoderLayer(d, config.transformer_heads, 4 * d, dropout=0.0, batch_first=True,
                                           norm_first=True)
        self.encoder = nn.TransformerEncoder(layer, config.transformer_layers, norm=nn.LayerNorm(d),
                                             enable_nested_tensor=False)
        self.heads = Heads(d, d, config)

    def initial_hidden(self, batch_size: int, device: torch.device | str | None = None) -> Hidden:
        c, device = self.config, self.device if device is None else device
        tokens = torch.zeros(batch_size, c.transformer_context, c.state_dim + c.action_dim, device=device)
        return tokens, torch.zeros(batch_size, c.transformer_context, dtype=torch.bool, device=device)

    def step(self, hidden: Hidden, state: torch.Tensor, action: torch.Tensor, member: torch.Tensor | None = None,
             next_state: torch.Tensor | None = None) -> tuple[Hidden, Prediction]:
        tokens = _push(hidden[0], torch.cat([state, action], dim=-1))
        valid = _push(hidden[1], torch.ones_like(hidden[1][:, 0]))
        x = self.embed(tokens) + self.position
        features = self.encoder(x, src_key_padding_mask=~valid)[:, -1]
        return (tokens, valid), self.heads(features, features, state, member)


class NoChangeModel(WorldModel):
    """Predicts that the state stays the same, no contact, no termination; nothing to train. Hidden = ()."""

    def initial_hidden(self, batch_size: int, device: torch.device | str | None = None) -> Hidden:
        return ()

    def step(self, hidden: Hidden, state: torch.Tensor, action: torch.Tensor, member: torch.Tensor | None = None,
             next_state: torch.Tensor | None = None) -> tuple[Hidden, Prediction]:
        c, batch = self.config, state.shape[0]
        zeros = state.new_zeros(batch)
        return (), Prediction(
            state_mean=state, state_std=torch.full_like(state, 1e-3),
            contact_logits=state.new_zeros(batch, c.contact_dim), foot_height=state.new_zeros(batch, c.foot_dim),
            termination_logit=torch.full_like(zeros, -10.0), uncertainty=zeros,
        )
