"""Fixed per-dimension normalisation of world-model inputs and targets, taken from the task spec.

States: (x - state_mean) / state_std with the spec's hand-set statistics (not running statistics, so a checkpoint
means the same thing whatever data it saw). Foot heights: height / foot_height_std. Actions pass unchanged (they
already live in [-1, 1]). The arrays are stored in every checkpoint.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from rwm_gym.spec import TaskSpec


@dataclass(frozen=True)
class Normalizer:
    """The state and foot-height scaling a world model trains and predicts in, saved in its checkpoint."""

    state_mean: np.ndarray
    """(S,) float64, in the state's units."""
    state_std: np.ndarray
    """(S,) float64, positive."""
    foot_height_std: float
    """m."""

    @classmethod
    def from_spec(cls, spec: TaskSpec) -> Normalizer:
        return cls(
            np.asarray(spec.state_mean, dtype=np.float64),
            np.asarray(spec.state_std, dtype=np.float64),
            float(spec.privileged.foot_height_std),
        )

    def _stats(self, like: np.ndarray | torch.Tensor) -> tuple:
        if isinstance(like, torch.Tensor):
            return (
                torch.as_tensor(self.state_mean, dtype=like.dtype, device=like.device),
                torch.as_tensor(self.state_std, dtype=like.dtype, device=like.device),
            )
        return self.state_mean.astype(like.dtype), self.state_std.astype(like.dtype)

    def normalize_state(self, state: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
        """(..., S) physical state -> normalised, same type and dtype."""
        mean, std = self._stats(state)
        return (state - mean) / std

    def denormalize_state(self, state: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
        """(..., S) normalised state -> physical units."""
        mean, std = self._stats(state)
        return state * std + mean

    def denormalize_std(self, std: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
        """(..., S) normalised standard deviation -> physical units."""
        return std * self._stats(std)[1]

    def normalize_foot_height(self, height: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
        return height / self.foot_height_std

    def denormalize_foot_height(self, height: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
        return height * self.foot_height_std
