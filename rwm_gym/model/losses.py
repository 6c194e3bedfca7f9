"""The dual-autoregressive training loss of one batch of windows, and the paper's relative prediction error.

Inner loop: the model warms up on the H true history rows. Outer loop: for F steps it predicts the next row and feeds
back a reparameterised sample of its own prediction with the true next action (gradients flow through the samples).
Every learned term is computed on the F forecast predictions:
- state: squared error of a sample (mean + std * eps) against the true state ("mse", as RWM) or the Gaussian NLL;
- contacts: BCE on the logits; foot heights: squared error (normalised);
- termination: BCE with `pos_weight` (negatives per positive) so that rare falls are not ignored;
- the log-std band sum(max) - sum(min) of the state heads (`WorldModel.regularization`);
- latent-variable models (RSSM) also reconstruct the warm-up rows from their posterior and pay the KL (free nats).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from rwm_gym.model.base import WorldModel
from rwm_gym.model.config import TrainConfig
from rwm_gym.model.prediction import Prediction
from rwm_gym.model.windows import Window


def _state_loss(prediction: Prediction, target: torch.Tensor, kind: str) -> torch.Tensor:
    if kind == "nll":
        z = (target - prediction.state_mean) / prediction.state_std
        return (0.5 * z.square() + prediction.state_std.log()).mean()
    return (prediction.sample() - target).square().mean()


def window_loss(model: WorldModel, batch: Window, config: TrainConfig, pos_weight: float,
                member: torch.Tensor | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """Total loss of a batch of windows of H + F rows, and its parts (floats, for logging).

    member: (B,) ensemble head per window (each head learns from its own windows), None for a single head.
    """
    h, f = config.history, config.forecast
    prediction, warm = model.forecast(batch.states[:, :h], batch.actions[:, :h + f - 1], f, sample=True,
                                      member=member)
    target = slice(h, h + f)
    parts = {"state": _state_loss(prediction, batch.states[:, target], config.loss)}
    if prediction.contact_logits.shape[-1]:
        parts["contact"] = config.contact_weight * F.binary_cross_entropy_with_logits(
            prediction.contact_logits, batch.contacts[:, target])
    if prediction.foot_height.shape[-1]:
        parts["foot"] = config.foot_weight * (prediction.foot_height - batch.foot_heights[:, target]).square().mean()
    parts["termination"] = config.termination_weight * F.binary_cross_entropy_with_logits(
        prediction.termination_logit, batch.terminated[:, target],
        pos_weight=torch.tensor(pos_weight, device=batch.states.device))
    parts["bound"] = config.bound_weight * model.regularization()
    if warm is not None and warm.kl is not None:
        parts["latent"] = (_state_loss(warm, batch.states[:, 1:h], config.loss)
                           + config.kl_weight * warm.kl.clamp(min=config.kl_free_nats).mean())
    total = sum(parts.values())
    return total, {name: float(value.detach()) for name, value in parts.items()}


def relative_error(predicted: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
    """RWM's error: sum |pred - true| / sum |true| over the last (state) dim, per row: (..., S) -> (...)."""
    return (predicted - true).abs().sum(-1) / true.abs().sum(-1).clamp(min=1e-8)
