"""Baseline world models under the RWM interface: an MLP over a short stacked history, a causal Transformer over a
bounded window, and "the state stays the same". The RSSM lives in `rssm.py`.

Their hidden state is the history they condition on, so the imagined env can reset and warm them up exactly like
the RWM.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from rwm_gym.model.base import Hidden, WorldModel
from rwm_gym.model.config import ModelConfig
from rwm_gym.model.heads import Heads
from rwm_gym.model.prediction import Prediction


def _history_trajectory(buffer: torch.Tensor, tokens: torch.Tensor) -> torch.Tensor:
    """The buffer after each of T pushes: buffer (B, K, ...), tokens (B, T, ...) -> (B, T, K, ...)."""
    windows = torch.cat([buffer, tokens], dim=1).unfold(1, buffer.shape[1], 1)[:, 1:]  # (B, T, ..., K)
    return windows.permute(0, 1, windows.dim() - 1, *range(2, windows.dim() - 1))


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

    def step(
        self,
        hidden: Hidden,
        state: torch.Tensor,
        action: torch.Tensor,
        member: torch.Tensor | None = None,
        next_state: torch.Tensor | None = None,
    ) -> tuple[Hidden, Prediction]:
        history = _push(hidden[0], torch.cat([state, action], dim=-1))
        features = self.trunk(history.flatten(1))
        return (history,), self.heads(features, features, state, member)

    def hidden_trajectory(
        self,
        hidden: Hidden,
        states: torch.Tensor,
        actions: torch.Tensor,
        member: torch.Tensor | None = None,
        next_states: torch.Tensor | None = None,
    ) -> tuple[Hidden, Prediction]:
        """The stacked histories of all T steps at once, and the trunk over all of them in one batch."""
        histories = _history_trajectory(hidden[0], torch.cat([states, actions], dim=-1))  # (B, T, K, S + A)
        features = self.trunk(histories.flatten(2))
        return (histories,), self.heads(features, features, states, member)


class TransformerModel(WorldModel):
    """Causal Transformer encoder over the last K = `transformer_context` (state, action) tokens; reads out the newest.

    Hidden = (tokens (B, K, S + A), valid (B, K) bool), oldest first; the valid tokens are the newest ones (a
    suffix), empty slots before the first steps are invalid. Every token attends to itself and to the valid tokens
    before it (causal), with a learned per-head bias by distance (relative positions). A token's features therefore do
    not depend on the slot it sits in, and `observe` runs known steps as one causal pass over [context, new tokens]
    that equals stepping; `step` (the forecast) appends a token and encodes the bounded window again.
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__(config)
        d = config.transformer_dim
        self.embed = nn.Linear(config.state_dim + config.action_dim, d)
        self.distance_bias = nn.Parameter(torch.zeros(config.transformer_heads, config.transformer_context))
        # ELU as in the other models; unlike ReLU/GELU it also keeps PyTorch's inference fast path off, which turns
        # the per-head float mask (distance bias) into NaNs (torch 2.13).
        layer = nn.TransformerEncoderLayer(
            d, config.transformer_heads, 4 * d, dropout=0.0, activation=F.elu, batch_first=True, norm_first=True
        )
        self.encoder = nn.TransformerEncoder(
            layer, config.transformer_layers, norm=nn.LayerNorm(d), enable_nested_tensor=False
        )
        self.heads = Heads(d, d, config)

    def initial_hidden(self, batch_size: int, device: torch.device | str | None = None) -> Hidden:
        c, device = self.config, self.device if device is None else device
        tokens = torch.zeros(batch_size, c.transformer_context, c.state_dim + c.action_dim, device=device)
        return tokens, torch.zeros(batch_size, c.transformer_context, dtype=torch.bool, device=device)

    def _encode(self, tokens: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """Features (B, L, d) of tokens (B, L, S + A), each attending causally to the valid tokens (B, L) at most
        K - 1 rows back, with the distance bias. Invalid tokens attend to themselves only (finite, never read)."""
        length, context = tokens.shape[1], self.config.transformer_context
        rows = torch.arange(length, device=tokens.device)
        distance = rows[:, None] - rows[None, :]  # (L, L): query row - key row
        allowed = (distance >= 0) & (distance < context) & (valid[:, None, :] | (distance == 0))  # (B, L, L)
        bias = self.distance_bias[:, distance.clamp(0, context - 1)]  # (heads, L, L)
        mask = torch.where(allowed[:, None], bias, float("-inf")).flatten(0, 1)  # (B * heads, L, L)
        return self.encoder(self.embed(tokens), mask=mask)

    def observe(
        self,
        hidden: Hidden,
        states: torch.Tensor,
        actions: torch.Tensor,
        member: torch.Tensor | None = None,
        next_states: torch.Tensor | None = None,
    ) -> tuple[Hidden, Prediction]:
        """The steps that fit into the context beside the valid tokens run as one causal pass; any further ones
        step by step (once old tokens leave the window, the bounded context is inherently per step)."""
        tokens, valid = hidden
        context, length = self.config.transformer_context, states.shape[1]
        kept = int(valid.sum(1).max())
        fit = min(length, context - kept)
        if fit == 0:
            return super().observe(hidden, states, actions, member, next_states)
        new = torch.cat([states[:, :fit], actions[:, :fit]], dim=-1)
        features = self._encode(
            torch.cat([tokens[:, context - kept :], new], dim=1),
            torch.cat([valid[:, context - kept :], valid.new_ones(valid.shape[0], fit)], dim=1),
        )
        features = features[:, kept:]
        prediction = self.heads(features, features, states[:, :fit], member)
        hidden = (
            torch.cat([tokens, new], dim=1)[:, -context:],
            torch.cat([valid, valid.new_ones(valid.shape[0], fit)], dim=1)[:, -context:],
        )
        if fit == length:
            return hidden, prediction
        hidden, rest = super().observe(
            hidden, states[:, fit:], actions[:, fit:], member, None if next_states is None else next_states[:, fit:]
        )
        return hidden, Prediction.cat([prediction, rest])

    def step(
        self,
        hidden: Hidden,
        state: torch.Tensor,
        action: torch.Tensor,
        member: torch.Tensor | None = None,
        next_state: torch.Tensor | None = None,
    ) -> tuple[Hidden, Prediction]:
        tokens = _push(hidden[0], torch.cat([state, action], dim=-1))
        valid = _push(hidden[1], torch.ones_like(hidden[1][:, 0]))
        features = self._encode(tokens, valid)[:, -1]
        return (tokens, valid), self.heads(features, features, state, member)

    def hidden_trajectory(
        self,
        hidden: Hidden,
        states: torch.Tensor,
        actions: torch.Tensor,
        member: torch.Tensor | None = None,
        next_states: torch.Tensor | None = None,
    ) -> tuple[Hidden, None]:
        """The token windows after each of T steps, without encoding them (a forecast re-encodes its own window, so
        predictions on a long sequence would cost one encoding per step: None)."""
        tokens = _history_trajectory(hidden[0], torch.cat([states, actions], dim=-1))
        valid = _history_trajectory(hidden[1], hidden[1].new_ones(states.shape[:2]))
        return (tokens, valid), None


class NoChangeModel(WorldModel):
    """Predicts that the state stays the same, no contact, no termination; nothing to train. Hidden = ()."""

    def initial_hidden(self, batch_size: int, device: torch.device | str | None = None) -> Hidden:
        return ()

    def step(
        self,
        hidden: Hidden,
        state: torch.Tensor,
        action: torch.Tensor,
        member: torch.Tensor | None = None,
        next_state: torch.Tensor | None = None,
    ) -> tuple[Hidden, Prediction]:
        c, batch = self.config, state.shape[0]
        zeros = state.new_zeros(batch)
        return (), Prediction(
            state_mean=state,
            state_std=torch.full_like(state, 1e-3),
            contact_logits=state.new_zeros(batch, c.contact_dim),
            foot_height=state.new_zeros(batch, c.foot_dim),
            termination_logit=torch.full_like(zeros, -10.0),
            uncertainty=zeros,
        )
