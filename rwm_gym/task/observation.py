"""The policy observation: state groups, command and last action, in the order the spec lists them."""

from __future__ import annotations

import numpy as np

from rwm_gym.spec import TaskSpec


def observation_slices(spec: TaskSpec) -> dict[str, slice]:
    """Where each observation group sits in the observation vector."""
    sizes = {g.name: g.size for g in spec.state}
    sizes["command"] = len(spec.command.names)
    sizes["last_action"] = spec.action_dim
    out, start = {}, 0
    for name in spec.observation.groups:
        out[name] = slice(start, start + sizes[name])
        start += sizes[name]
    return out


def observation_parts(spec: TaskSpec, state, command, last_action) -> list:
    """The observation's groups in the spec's order, each (N, size): slices of state (N, S), command (N, K) and last
    action (N, A), numpy arrays or torch tensors alike (a differentiable learner builds its observation from these)."""
    slices = spec.state_slices
    by_name = {"command": command, "last_action": last_action}
    return [by_name[name] if name in by_name else state[:, slices[name]] for name in spec.observation.groups]


def build_observation(
    spec: TaskSpec,
    state: np.ndarray,
    command: np.ndarray,
    last_action: np.ndarray,
    noise_rngs: list[np.random.Generator] | None = None,
) -> np.ndarray:
    """Observation (N, O) from state (N, S), command (N, K) and last action (N, A).

    With `noise_rngs` (one generator per env), each group gets uniform noise of the spec's half-width.
    """
    parts = []
    for name, part in zip(spec.observation.groups, observation_parts(spec, state, command, last_action), strict=True):
        part = np.asarray(part, dtype=np.float32)
        width = spec.observation.noise.get(name, 0.0)
        if noise_rngs is not None and width > 0:
            noise = np.stack([rng.uniform(-width, width, part.shape[1]) for rng in noise_rngs])
            part = part + noise.astype(np.float32)
        parts.append(part)
    return np.concatenate(parts, axis=1)
