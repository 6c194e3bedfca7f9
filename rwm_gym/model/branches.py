"""Forecast branches: many autoregressive forecasts trained from one teacher-forced pass over a segment.

The paper's window spends H - 1 of its H + F recurrent steps on the teacher-forced warm-up and F on the forecast that
carries the loss. Here a segment of `TrainConfig.segment_rows` rows is warmed up once (one sequence pass, keeping the
hidden state after every row), and `branches` F-step forecasts start from it: branch i takes row j_i = H - 1 + i *
branch_stride as its last true row (its history is rows 0..j_i, at least H of them), then predicts rows j_i + 1 ..
j_i + F feeding back a reparameterised sample of its own prediction (mean + std * eps, gradients through it) with the
true actions, exactly like `WorldModel.forecast`. All branches step together, one batched call per forecast step.

By default nothing is truncated: a branch's gradient flows through its forecast into the hidden state it started from
and on through the teacher-forced pass, as in the paper's window. With `TrainConfig.warmup_gradients` off, the pass
runs without autograd and every branch steps from its detached hidden state (its first step recomputed with
gradients): truncated backpropagation at the forecast's start, the warm-up's backward pass saved. What differs from
the paper's windows: branch histories are longer than H (up to H + (branches - 1) * branch_stride rows) and the
branches of a segment share data. When the model's predictions on known rows are forecasts that carry gradients
(`hidden_trajectory` returns them: RWM, MLP), a branch's first step is read from the teacher-forced pass instead of
being recomputed, so it costs F - 1 batched steps. With one branch the numbers equal
`WorldModel.forecast` on an H + F window.
"""

from __future__ import annotations

import torch

from rwm_gym.model.base import WorldModel
from rwm_gym.model.config import TrainConfig
from rwm_gym.model.prediction import Prediction


def branch_starts(config: TrainConfig) -> torch.Tensor:
    """(branches,) long: the last true row of each branch within a segment."""
    return config.history - 1 + config.branch_stride * torch.arange(config.branches)


def branch_rows(config: TrainConfig, device: torch.device | str = "cpu") -> torch.Tensor:
    """(branches, F) long: the segment rows each branch predicts (row j_i + 1 + k at forecast step k)."""
    return (branch_starts(config).unsqueeze(1) + 1 + torch.arange(config.forecast)).to(device)


def _at(tensor: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """tensor (B, T, ...) at rows (n,) or (n, F) of dim 1, flattened to (B * n, ...) or (B * n, F, ...)."""
    return tensor[:, rows].flatten(0, 1)


def branched_forecast(
    model: WorldModel,
    states: torch.Tensor,
    actions: torch.Tensor,
    config: TrainConfig,
    member: torch.Tensor | None = None,
) -> tuple[Prediction, Prediction | None]:
    """Train-mode forecasts of all branches of a batch of segments.

    states (B, R, S), actions (B, R, A): normalised segment rows, R = config.segment_rows. member: (B,) ensemble head
    per segment (all its branches use it) or None. Returns (predictions (B * branches, F, ...), segment-major: row
    b * branches + i is branch i of segment b; for latent-variable models, the teacher-forced predictions (B, T, ...)
    of rows 1..T with their KL, for their own loss, else None).
    """
    if not config.warmup_gradients and model.filters_with_next_state:
        raise ValueError(
            f"warmup_gradients off does not apply to {model.config.kind}: its teacher-forced pass carries "
            "a loss of its own"
        )
    starts = branch_starts(config).to(states.device)
    last = int(starts[-1])
    initial = model.initial_hidden(states.shape[0], states.device)
    # The pass observes rows 0..last or, for a model that filters with the next state, 0..last - 1. First steps are
    # read from it where its predictions are forecasts that carry gradients, else recomputed.
    observed = last if model.filters_with_next_state else last + 1
    reuse = not model.filters_with_next_state and config.warmup_gradients
    with torch.set_grad_enabled(torch.is_grad_enabled() and config.warmup_gradients):
        trajectory, predictions = model.hidden_trajectory(
            initial, states[:, :observed], actions[:, :observed], member, next_states=states[:, 1 : observed + 1]
        )
    reuse = reuse and predictions is not None
    # hidden after rows 0..t sits at index t + 1 of `before` (index 0: the initial state)
    before = tuple(torch.cat([h0.unsqueeze(1), h], dim=1) for h0, h in zip(initial, trajectory, strict=True))
    branch_member = None if member is None else member.repeat_interleave(config.branches)
    rows = branch_rows(config, states.device)  # (n, F) predicted rows; the input of step k is row rows[:, k] - 1
    step_actions = _at(actions, rows - 1)  # (B * n, F, A)
    forecasts = []
    if reuse:
        hidden = tuple(_at(h, starts + 1) for h in before)
        forecasts.append(predictions.map(lambda t: _at(t, starts)))
    else:
        hidden = tuple(_at(h, starts) for h in before)
    x = _at(states, starts)
    for k in range(len(forecasts), config.forecast):
        if k > 0:
            x = forecasts[-1].sample()
        hidden, p = model.step(hidden, x, step_actions[:, k], branch_member)
        forecasts.append(p)
    warm = predictions if predictions is not None and predictions.kl is not None else None
    return Prediction.stack(forecasts), warm
