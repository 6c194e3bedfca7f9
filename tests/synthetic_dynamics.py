"""Tiny learnable datasets for the world-model tests: a stable linear system in normalised units, with the real
ANYmal D spec text, episodes of different lengths, contacts and foot heights that depend on the state, and falls.

s'_{t+1} = M s'_t + N a_t + noise in normalised units (M damped planar rotations of pairs of dims, so "no change" is a
poor guess); the stored states are de-normalised with the spec's statistics, as real data would be.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rwm_gym.data.dataset import DatasetInfo, write_dataset
from rwm_gym.spec import TaskSpec, load_spec

SPEC = load_spec("anymal_d")


def info_for(spec: TaskSpec = SPEC) -> DatasetInfo:
    return DatasetInfo(
        env_id=spec.physics_env_id,
        spec_text=spec.text,
        dt=spec.policy_dt,
        columns={"state": list(spec.state_columns), "action": list(spec.actuator.joints)},
        policy="synthetic linear system",
        seed=0,
        physics_params={},
    )


def linear_episodes(
    num_episodes: int = 12, rows: tuple[int, int] = (40, 70), seed: int = 0, spec: TaskSpec = SPEC
) -> list[dict[str, np.ndarray]]:
    rng = np.random.default_rng(seed)
    s_dim, a_dim = spec.state_dim, spec.action_dim
    m = 0.98 * np.eye(s_dim)
    for i in range(0, s_dim - 1, 2):  # planar rotations of pairs of dims, 0.1 to 0.3 rad per step
        angle = 0.1 + 0.2 * i / s_dim
        m[i : i + 2, i : i + 2] = 0.98 * np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    n = np.random.default_rng(124).normal(size=(s_dim, a_dim)) * 0.1
    episodes = []
    for e in range(num_episodes):
        length = int(rng.integers(*rows))
        z = np.zeros((length, s_dim))
        a = np.zeros((length, a_dim))
        z[0] = rng.normal(size=s_dim)
        for t in range(length - 1):
            a[t] = np.clip(0.8 * a[t - 1] + 0.3 * rng.normal(size=a_dim), -1, 1) if t else rng.uniform(-1, 1, a_dim)
            z[t + 1] = m @ z[t] + n @ a[t] + 0.01 * rng.normal(size=s_dim)
        terminated = np.zeros(length, bool)
        truncated = np.zeros(length, bool)
        (terminated if e % 3 == 0 else truncated)[-1] = True
        episodes.append(
            {
                "state": (z * spec.state_std + spec.state_mean).astype(np.float32),
                "action": a.astype(np.float32),
                "contact": z[:, : spec.contact_dim] > 0,
                "foot_height": (0.05 * np.tanh(z[:, : spec.foot_dim])).astype(np.float32),
                "terminated": terminated,
                "truncated": truncated,
                "command": np.zeros((length, len(spec.command.names)), np.float32),
                "reward": np.zeros(length, np.float32),
                "qpos": np.zeros((length, 1)),
                "qvel": np.zeros((length, 1)),
            }
        )
    return episodes


def write_linear_dataset(path: Path, **kwargs) -> Path:
    spec = kwargs.get("spec", SPEC)
    write_dataset(path, info_for(spec), linear_episodes(**kwargs))
    return path
