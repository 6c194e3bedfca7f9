"""Policies that drive collections: random exploration, zero actions, or a trained SB3 policy (the scripted gait is
`rwm_gym.policies.gait`; `rwm_gym.policies.factory.make_policy` picks one by name).

Every policy is vectorised over N envs and follows one small protocol:
`reset(ids, rngs)` at the start of episodes in envs `ids` (one generator each, so the data is deterministic), and
`act(obs) -> actions` with obs (N, O) and actions (N, A) in [-1, 1].
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

import numpy as np

from rwm_gym.spec import TaskSpec


class Policy(Protocol):
    """A batched scripted policy: `reset` envs `ids` with their generators, `act` on (N, O) observations."""

    name: str

    def reset(self, ids: np.ndarray, rngs: list[np.random.Generator]) -> None: ...

    def act(self, obs: np.ndarray) -> np.ndarray: ...


def gaussian_noise(rngs: list[np.random.Generator], std: float, dim: int) -> np.ndarray:
    """(N, dim) action noise, each env's row drawn from its own generator (so the data is deterministic)."""
    return np.stack([rng.normal(0.0, std, dim) for rng in rngs])


class RandomPolicy:
    """Temporally correlated random actions: a(t) = rho * a(t-1) + sqrt(1 - rho^2) * sigma * eps, clipped to [-1, 1].

    rho = 0 is white noise; rho near 1 gives slow, large motions that explore the state space better.
    """

    name = "random"

    def __init__(self, spec: TaskSpec, num_envs: int, *, correlation: float = 0.9, scale: float = 0.5):
        self.correlation, self.scale = correlation, scale
        self.actions = np.zeros((num_envs, spec.action_dim))
        self.rngs: list[np.random.Generator] = [np.random.default_rng(0) for _ in range(num_envs)]

    def reset(self, ids: np.ndarray, rngs: list[np.random.Generator]) -> None:
        for i, rng in zip(ids, rngs):
            self.rngs[i] = rng
            self.actions[i] = rng.normal(0.0, self.scale, self.actions.shape[1])

    def act(self, obs: np.ndarray) -> np.ndarray:
        rho = self.correlation
        noise = gaussian_noise(self.rngs, self.scale, self.actions.shape[1])
        self.actions = rho * self.actions + np.sqrt(1.0 - rho**2) * noise
        return np.clip(self.actions, -1.0, 1.0)


class ZeroPolicy:
    """Zero actions (the default pose: the robot stands still, the tracking score's floor), plus optional Gaussian
    noise; its episodes are the standing states every physics episode starts from."""

    name = "zero"

    def __init__(self, spec: TaskSpec, num_envs: int, *, action_noise: float = 0.0):
        self.action_noise, self.action_dim = action_noise, spec.action_dim
        self.rngs: list[np.random.Generator] = [np.random.default_rng(0) for _ in range(num_envs)]

    def reset(self, ids: np.ndarray, rngs: list[np.random.Generator]) -> None:
        for i, rng in zip(ids, rngs):
            self.rngs[i] = rng

    def act(self, obs: np.ndarray) -> np.ndarray:
        actions = np.zeros((obs.shape[0], self.action_dim))
        if self.action_noise > 0:
            actions = actions + gaussian_noise(self.rngs, self.action_noise, self.action_dim)
        return np.clip(actions, -1.0, 1.0)


class SB3Policy:
    """A trained Stable-Baselines3 policy (a `.zip` from `model.save`, loaded without running code from it), acting
    deterministically, plus optional noise."""

    def __init__(
        self, path: str | Path, spec: TaskSpec, num_envs: int, *, action_noise: float = 0.0, algorithm: str = "PPO"
    ):
        from rwm_gym.policy_zip import load_policy

        self.model = load_policy(path, device="cpu", spec=spec, algorithm=algorithm)
        self.name = f"sb3:{Path(path).name}"
        self.action_noise = action_noise
        self.rngs: list[np.random.Generator] = [np.random.default_rng(0) for _ in range(num_envs)]
        self.action_dim = spec.action_dim

    def reset(self, ids: np.ndarray, rngs: list[np.random.Generator]) -> None:
        for i, rng in zip(ids, rngs):
            self.rngs[i] = rng

    def act(self, obs: np.ndarray) -> np.ndarray:
        actions, _ = self.model.predict(obs.astype(np.float32), deterministic=True)
        if self.action_noise > 0:
            actions = actions + gaussian_noise(self.rngs, self.action_noise, self.action_dim)
        return np.clip(actions, -1.0, 1.0)
