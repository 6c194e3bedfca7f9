"""What a world model predicts for the next row, batch first, in normalised units."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, fields

import torch


@dataclass
class Prediction:
    """What a model predicts for the next row; shapes (B, ...) from `step`, (B, T, ...) from `observe`/`forecast`."""

    state_mean: torch.Tensor
    """(B, S) absolute next normalised state (the residual is already added to the input state)."""
    state_std: torch.Tensor
    """(B, S) standard deviation of the next normalised state."""
    contact_logits: torch.Tensor
    """(B, C) logits of the contact flags."""
    foot_height: torch.Tensor
    """(B, F) foot heights divided by the spec's foot_height_std."""
    termination_logit: torch.Tensor
    """(B,) logit of "the next row is a terminal state"."""
    uncertainty: torch.Tensor | None
    """(B,) ensemble disagreement: mean over dims of the std of the members' means (zeros for one member); None where
    the caller asked not to compute it (`WorldModel.computing_disagreement(False)`)."""
    kl: torch.Tensor | None = None
    """(B,) KL(posterior || prior) of a latent-variable model, only when the true next state was given."""

    def sample(self) -> torch.Tensor:
        """Reparameterised sample mean + std * eps of the next state (gradients flow through it)."""
        return self.state_mean + self.state_std * torch.randn_like(self.state_std)

    def map(self, fn: Callable[[torch.Tensor], torch.Tensor]) -> Prediction:
        """A Prediction with `fn` applied to every tensor (e.g. indexing)."""
        return Prediction(
            **{f.name: None if getattr(self, f.name) is None else fn(getattr(self, f.name)) for f in fields(self)}
        )

    @staticmethod
    def stack(predictions: Sequence[Prediction], dim: int = 1) -> Prediction:
        """Stack per-step predictions along a new time dim (default 1: (B, T, ...))."""
        first = predictions[0]
        return Prediction(
            **{
                f.name: None
                if getattr(first, f.name) is None
                else torch.stack([getattr(p, f.name) for p in predictions], dim)
                for f in fields(first)
            }
        )

    @staticmethod
    def cat(predictions: Sequence[Prediction], dim: int = 1) -> Prediction:
        """Concatenate predictions of consecutive steps along their time dim (default 1: (B, T1 + T2 + ..., ...))."""
        first = predictions[0]
        return Prediction(
            **{
                f.name: None
                if getattr(first, f.name) is None
                else torch.cat([getattr(p, f.name) for p in predictions], dim)
                for f in fields(first)
            }
        )
