"""The one interface every world model implements: `step(hidden, state, action) -> (hidden, prediction)`.

Everything is in normalised units (see `normalization.py`): states are `(x - mean) / std` with the task spec's fixed
statistics, foot heights are divided by the spec's `foot_height_std`, actions are passed as they are (in [-1, 1]).

The hidden state is explicit: a tuple of tensors, each with the batch on dim 0, so that an environment holding many
rollouts can pick, overwrite or reset some of them with `select_hidden`, `scatter_hidden(_)` and `reset_hidden` without
knowing the model's kind. Causal alignment: `step(h, state[t], action[t])` predicts `state[t+1]` (and the contacts,
foot heights and termination flag of row t+1).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch
from torch import nn

from rwm_gym.model.config import ModelConfig
from rwm_gym.model.heads import StateHead
from rwm_gym.model.prediction import Prediction

Hidden = tuple[torch.Tensor, ...]
"""A model's recurrent state: tensors with the batch on dim 0 (an empty tuple for memoryless models)."""


class WorldModel(nn.Module):
    """Base class of all world models. Subclasses implement `initial_hidden` and `step` (or `observe`, see below).

    `step` predicts one row ahead; `observe` runs many known steps at once (the default loops over `step`; recurrent
    models override it with a sequence kernel and then define `step` through it); `warm_up` and `forecast` build the
    history-then-open-loop rollouts used by training, evaluation and the imagined environment.
    """

    filters_with_next_state = False
    """True when `step` uses the true next state (a posterior); then its predictions on known steps are no forecasts."""
    warm_hidden_reads_member = True
    """False when `warm_hidden` ignores the ensemble member: a history's warm state then serves every member and can
    be cached (`rwm_gym.imagination.reset_data.WarmUpCache`)."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        self.register_buffer("_anchor", torch.zeros(0), persistent=False)  # device of a model without parameters

    @property
    def device(self) -> torch.device:
        return self._anchor.device

    def initial_hidden(self, batch_size: int, device: torch.device | str | None = None) -> Hidden:
        """The hidden state before any step (zeros / an empty history) for `batch_size` rollouts."""
        raise NotImplementedError

    def step(
        self,
        hidden: Hidden,
        state: torch.Tensor,
        action: torch.Tensor,
        member: torch.Tensor | None = None,
        next_state: torch.Tensor | None = None,
    ) -> tuple[Hidden, Prediction]:
        """Advance one step. state (B, S) normalised, action (B, A) -> (new hidden, prediction of row t+1).

        member: (B,) long, the ensemble head used by each rollout; None averages the heads.
        next_state: (B, S) true next state when known (history); only latent-variable models (RSSM) use it, to
        filter with the posterior. Leave None when predicting.
        """
        raise NotImplementedError

    def observe(
        self,
        hidden: Hidden,
        states: torch.Tensor,
        actions: torch.Tensor,
        member: torch.Tensor | None = None,
        next_states: torch.Tensor | None = None,
    ) -> tuple[Hidden, Prediction]:
        """Run known steps: states (B, T, S), actions (B, T, A) -> (hidden after T steps, predictions (B, T, ...))."""
        predictions = []
        for t in range(states.shape[1]):
            hidden, p = self.step(
                hidden, states[:, t], actions[:, t], member, None if next_states is None else next_states[:, t]
            )
            predictions.append(p)
        return hidden, Prediction.stack(predictions)

    def hidden_trajectory(
        self,
        hidden: Hidden,
        states: torch.Tensor,
        actions: torch.Tensor,
        member: torch.Tensor | None = None,
        next_states: torch.Tensor | None = None,
    ) -> tuple[Hidden, Prediction | None]:
        """Run T known steps like `observe`, keeping the hidden state after every step: each tensor (B, T, ...).

        Also returns the predictions (B, T, ...) of the steps, or None where they would cost extra (the Transformer).
        They are forecasts (a branch may start from them) unless the model filters with `next_states`
        (`filters_with_next_state`). The default steps one row at a time; models with a sequence kernel or a history
        buffer override it.
        """
        trajectory, predictions = [], []
        for t in range(states.shape[1]):
            hidden, p = self.step(
                hidden, states[:, t], actions[:, t], member, None if next_states is None else next_states[:, t]
            )
            trajectory.append(hidden)
            predictions.append(p)
        if not trajectory:  # no step: empty (B, 0, ...) trajectories
            return tuple(h.unsqueeze(1)[:, :0] for h in hidden), None
        return tuple(torch.stack(h, 1) for h in zip(*trajectory)), Prediction.stack(predictions)

    def warm_up(
        self, states: torch.Tensor, actions: torch.Tensor, member: torch.Tensor | None = None
    ) -> tuple[Hidden, Prediction | None]:
        """Hidden state after a true history, ready to `step` from its last state.

        states (B, H, S): true rows s_0..s_{H-1}; actions (B, >= H-1, A): a_0..a_{H-2} are used. The model observes
        (s_t, a_t, s_{t+1}) for t < H-1; the caller then steps with (s_{H-1}, a_{H-1}). Returns the hidden state and
        the warm-up predictions (B, H-1, ...) (None when H == 1).
        """
        batch, history = states.shape[:2]
        hidden = self.initial_hidden(batch, states.device)
        if history == 1:
            return hidden, None
        return self.observe(hidden, states[:, :-1], actions[:, : history - 1], member, next_states=states[:, 1:])

    def warm_hidden(self, states: torch.Tensor, actions: torch.Tensor, member: torch.Tensor | None = None) -> Hidden:
        """`warm_up`'s hidden state alone, for callers that discard its predictions (an imagined env's reset).
        The default runs `warm_up`; models whose recurrence does not read the heads skip them."""
        return self.warm_up(states, actions, member)[0]

    @contextmanager
    def computing_disagreement(self, enabled: bool) -> Iterator[None]:
        """Within the block, ensemble heads compute their disagreement (`Prediction.uncertainty`) only if `enabled`;
        off, each rollout given a `member` runs only that head (k times fewer head FLOPs) and `uncertainty` is None."""
        heads = [m for m in self.modules() if isinstance(m, StateHead)]
        before = [h.disagreement for h in heads]
        self.set_disagreement(enabled)
        try:
            yield
        finally:
            for h, flag in zip(heads, before):
                h.disagreement = flag

    def set_disagreement(self, enabled: bool) -> None:
        """`computing_disagreement` for good, for an owner that decides once (an imagined env's own model)."""
        for module in self.modules():
            if isinstance(module, StateHead):
                module.disagreement = enabled

    def forecast(
        self,
        states: torch.Tensor,
        actions: torch.Tensor,
        horizon: int,
        *,
        sample: bool,
        member: torch.Tensor | None = None,
    ) -> tuple[Prediction, Prediction | None]:
        """Warm up on a true history, then predict `horizon` rows open-loop, feeding back the own predictions.

        states (B, H, S) true history s_0..s_{H-1}; actions (B, H + horizon - 1, A) the true actions a_0.. .
        Step k (0-based) feeds back the previous prediction: a reparameterised sample if `sample` (training, gradients
        flow through it) else its mean (evaluation). Returns (predictions of s_H..s_{H+horizon-1}, (B, horizon, ...);
        warm-up predictions or None).
        """
        history = states.shape[1]
        if actions.shape[1] < history + horizon - 1:
            raise ValueError(f"forecast needs {history + horizon - 1} actions, got {actions.shape[1]}")
        hidden, warm = self.warm_up(states, actions, member)
        x, predictions = states[:, -1], []
        for k in range(horizon):
            hidden, p = self.step(hidden, x, actions[:, history - 1 + k], member)
            predictions.append(p)
            if k + 1 < horizon:
                x = p.sample() if sample else p.state_mean
        return Prediction.stack(predictions), warm

    def regularization(self) -> torch.Tensor:
        """Extra training loss of the parameters: the width of the learned log-std band of every state head."""
        total = torch.zeros((), device=self.device)
        for module in self.modules():
            if isinstance(module, StateHead):
                total = total + module.bound_loss()
        return total

    @staticmethod
    def select_hidden(hidden: Hidden, index: torch.Tensor) -> Hidden:
        """The hidden states of some rollouts: index is (n,) long or (B,) bool."""
        return tuple(h[index] for h in hidden)

    @staticmethod
    def scatter_hidden(hidden: Hidden, index: torch.Tensor, values: Hidden) -> Hidden:
        """A copy of `hidden` with rollouts `index` ((n,) long) replaced by `values` (batch n)."""
        return tuple(h.index_copy(0, index, v.to(h.dtype)) for h, v in zip(hidden, values, strict=True))

    @staticmethod
    def scatter_hidden_(hidden: Hidden, index: torch.Tensor, values: Hidden) -> None:
        """`scatter_hidden` in place, for a holder that alone owns `hidden` (the imagined env between steps): no
        copy of every rollout's state to restart a few."""
        for h, v in zip(hidden, values, strict=True):
            h.index_copy_(0, index, v.to(h.dtype))

    def reset_hidden(self, hidden: Hidden, mask: torch.Tensor) -> Hidden:
        """A copy of `hidden` with the rollouts where mask ((B,) bool) is true set back to `initial_hidden`.

        Prefer `warm_up` on a real history for restarted rollouts: a cold hidden state predicts poorly.
        """
        fresh = self.initial_hidden(mask.shape[0], mask.device)
        return tuple(
            torch.where(mask.view(-1, *([1] * (h.dim() - 1))), f, h) for h, f in zip(hidden, fresh, strict=True)
        )
