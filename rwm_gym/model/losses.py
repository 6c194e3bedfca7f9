"""The dual-autoregressive training loss, and the paper's relative prediction error.

Inner loop: the model warms up on true history rows. Outer loop: for F steps it predicts the next row and feeds back a
reparameterised sample of its own prediction with the true next action (gradients flow through the samples).
`window_loss` does this on windows of H + F rows (the paper's recipe); `segment_loss` on segments that carry many
forecast branches each (`branches.py`). Every learned term is computed on the F forecast predictions:
- state: squared error of a sample (mean + std * eps) against the true state ("mse", as RWM) or the Gaussian NLL;
- contacts: BCE on the logits; foot heights: squared error (normalised);
- termination: BCE with `pos_weight` (negatives per positive) so that rare falls are not ignored;
- the width of the state heads' log-std band, sum(max - min) where positive (`WorldModel.regularization`);
- latent-variable models (RSSM) also reconstruct the warm-up rows from their posterior and pay the KL (free nats).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from rwm_gym.model.base import WorldModel
from rwm_gym.model.branches import branch_rows, branched_forecast
from rwm_gym.model.config import TrainConfig
from rwm_gym.model.prediction import Prediction
from rwm_gym.model.windows import Window


def _mean(values: torch.Tensor, weight: torch.Tensor | None) -> torch.Tensor:
    """Mean of values (N, ...); with weight (N,), the weighted mean over N of each row's mean."""
    if weight is None:
        return values.mean()
    per_row = values.reshape(len(values), -1).mean(1)
    return (per_row * weight).sum() / weight.sum()


def _state_loss(
    prediction: Prediction, target: torch.Tensor, kind: str, weight: torch.Tensor | None = None
) -> torch.Tensor:
    if kind == "nll":
        z = (target - prediction.state_mean) / prediction.state_std
        return _mean(0.5 * z.square() + prediction.state_std.log(), weight)
    return _mean((prediction.sample() - target).square(), weight)


def forecast_loss(
    model: WorldModel,
    prediction: Prediction,
    target: Window,
    warm: Prediction | None,
    warm_target: torch.Tensor | None,
    config: TrainConfig,
    pos_weight: float,
    weight: torch.Tensor | None = None,
    warm_weight: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The total loss and its parts from forecasts (N, F, ...) and their true rows `target` (N, F, ...).

    warm / warm_target: a latent-variable model's teacher-forced predictions and the true rows they predict.
    weight: (N,) 1 for the forecasts that count, 0 for those that ran past their episode's end (None: all count);
    warm_weight: (B, T) the same for the teacher-forced rows.
    """
    parts = {"state": _state_loss(prediction, target.states, config.loss, weight)}
    if prediction.contact_logits.shape[-1]:
        parts["contact"] = config.contact_weight * _mean(
            F.binary_cross_entropy_with_logits(prediction.contact_logits, target.contacts, reduction="none"), weight
        )
    if prediction.foot_height.shape[-1]:
        parts["foot"] = config.foot_weight * _mean((prediction.foot_height - target.foot_heights).square(), weight)
    parts["termination"] = config.termination_weight * _mean(
        F.binary_cross_entropy_with_logits(
            prediction.termination_logit,
            target.terminated,
            reduction="none",
            pos_weight=torch.tensor(pos_weight, device=target.states.device),
        ),
        weight,
    )
    parts["bound"] = config.bound_weight * model.regularization()
    if warm is not None and warm.kl is not None:
        flat = warm.map(lambda t: t.flatten(0, 1))  # (B * T, ...): one row per teacher-forced step
        row_weight = None if warm_weight is None else warm_weight.flatten()
        parts["latent"] = _state_loss(
            flat, warm_target.flatten(0, 1), config.loss, row_weight
        ) + config.kl_weight * _mean(flat.kl.clamp(min=config.kl_free_nats), row_weight)
    return sum(parts.values()), parts


def _detached(parts: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The parts for logging, left on the device: reading them (`float`) is a host copy the trainer makes only when it
    logs, never per step (on cuda each copy waits for the GPU)."""
    return {name: value.detach() for name, value in parts.items()}


def window_loss(
    model: WorldModel, batch: Window, config: TrainConfig, pos_weight: float, member: torch.Tensor | None = None
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Total loss of a batch of windows of H + F rows (the paper's recipe), and its parts (detached 0-dim tensors,
    for logging).

    member: (B,) ensemble head per window (each head learns from its own windows), None for a single head.
    """
    h, f = config.history, config.forecast
    prediction, warm = model.forecast(batch.states[:, :h], batch.actions[:, : h + f - 1], f, sample=True, member=member)
    target = batch.map(lambda t: t[:, h : h + f])
    total, parts = forecast_loss(model, prediction, target, warm, batch.states[:, 1:h], config, pos_weight)
    return total, _detached(parts)


def segment_loss(
    model: WorldModel,
    batch: Window,
    config: TrainConfig,
    pos_weight: float,
    member: torch.Tensor | None = None,
    real_rows: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Total loss of a batch of segments of `config.segment_rows` rows, each carrying `config.branches` forecasts,
    and its parts. member: (B,) ensemble head per segment, None for a single head. real_rows: (B,) long rows of each
    segment inside its episode (`WindowData.gather_clipped`); forecasts predicting a row past it do not count. With
    one branch this is `window_loss` (same numbers)."""
    prediction, warm = branched_forecast(model, batch.states, batch.actions, config, member)
    rows = branch_rows(config, batch.states.device)
    target = batch.map(lambda t: t[:, rows].flatten(0, 1))
    warm_target = None if warm is None else batch.states[:, 1 : warm.state_mean.shape[1] + 1]
    weight = warm_weight = None
    if real_rows is not None and not bool((real_rows > rows[-1, -1]).all()):
        weight = (rows[:, -1].unsqueeze(0) < real_rows.unsqueeze(1)).flatten().to(batch.states.dtype)
        if warm is not None:
            targets = torch.arange(1, warm.state_mean.shape[1] + 1, device=real_rows.device)
            warm_weight = (targets.unsqueeze(0) < real_rows.unsqueeze(1)).to(batch.states.dtype)
    total, parts = forecast_loss(model, prediction, target, warm, warm_target, config, pos_weight, weight, warm_weight)
    return total, _detached(parts)


class SegmentLoss(nn.Module):
    """`segment_loss` as a module around the model, so a data-parallel wrapper (DDP) can wrap one training step's
    forward: forward(batch, member, real_rows) -> (loss, parts)."""

    def __init__(self, model: WorldModel, config: TrainConfig, pos_weight: float) -> None:
        super().__init__()
        self.model, self.config, self.pos_weight = model, config, pos_weight

    def forward(
        self, batch: Window, member: torch.Tensor | None = None, real_rows: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        return segment_loss(self.model, batch, self.config, self.pos_weight, member, real_rows)


def relative_error(predicted: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
    """RWM's error: sum |pred - true| / sum |true| over the last (state) dim, per row: (..., S) -> (...)."""
    return (predicted - true).abs().sum(-1) / true.abs().sum(-1).clamp(min=1e-8)
