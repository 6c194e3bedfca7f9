"""Velocity commands (vx, vy, yaw rate): sampled at reset, resampled on a fixed period, per environment."""

from __future__ import annotations

import numpy as np

from rwm_gym.spec import CommandSpec


def sample_commands(spec: CommandSpec, rngs: list[np.random.Generator]) -> np.ndarray:
    """One command per generator, uniform in the spec's box; a `standing_fraction` of them are zero. (N, K)."""
    out = np.zeros((len(rngs), len(spec.names)), dtype=np.float32)
    for i, rng in enumerate(rngs):
        command = rng.uniform(spec.low, spec.high)
        out[i] = 0.0 if rng.uniform() < spec.standing_fraction else command
    return out


def resample_period(spec: CommandSpec, policy_dt: float) -> int:
    """Policy steps between two command draws."""
    return max(1, int(round(spec.resample_seconds / policy_dt)))
