"""The batched core: what every core provides and checks, whichever env or vector API wraps it.

A *core* steps N envs at once (the MuJoCo batch, the dm_control loop, the world model). It provides:

- `num_envs`, `single_observation_space`, `single_action_space`, `spec` (the TaskSpec);
- `reset(ids, seeds, commands=None) -> obs`: start new episodes in envs `ids` (array), seeding those whose seed is not
  None, holding `commands` (len(ids), K) for the episode where given; returns their observations, (len(ids), O);
- `step(actions) -> obs, reward, terminated, truncated, info`: every env one step, arrays with a leading N axis and
  `info` a dict of (N, ...) arrays; the core never resets on its own.

The single envs (`LocomotionEnv`, `DMCEnv`, `ImaginedEnv`) are a core with N = 1; the vector envs of `rwm_gym.vector`
wrap a core with N envs and reset finished ones automatically.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol

import gymnasium as gym
import numpy as np

from rwm_gym.spec import CommandSpec

MAX_NUM_ENVS = 16384
"""Most envs one core steps. Each physics env holds its own MjData and each imagined env a GRU state, so memory grows
linearly: a bound turns a typo (num_envs=100000) into an error instead of a machine that runs out of memory."""


class BatchedCore(Protocol):
    """N environments stepped together: the contract every physics and imagined core meets (arrays (N, ...))."""

    num_envs: int
    single_observation_space: gym.spaces.Box
    single_action_space: gym.spaces.Box

    def reset(
        self, ids: np.ndarray, seeds: Sequence[int | None] | None = None, commands: np.ndarray | None = None
    ) -> np.ndarray: ...

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]: ...


def check_num_envs(num_envs: Any) -> int:
    """`num_envs` as an int in 1..MAX_NUM_ENVS, or a one-line ValueError."""
    if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or not 1 <= num_envs <= MAX_NUM_ENVS:
        raise ValueError(f"num_envs must be an integer from 1 to {MAX_NUM_ENVS}, got {num_envs!r}")
    return int(num_envs)


def check_actions(actions: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """Validate a batch of actions: real, right shape, finite; clipped to [-1, 1]."""
    actions = np.asarray(actions)
    if actions.dtype.kind not in "biuf":
        raise ValueError(f"action has dtype {actions.dtype}, expected real numbers")
    actions = actions.astype(np.float64)
    if actions.shape != shape:
        raise ValueError(f"action has shape {actions.shape}, expected {shape}")
    if not np.all(np.isfinite(actions)):
        raise ValueError(
            f"action contains NaN or inf at env(s) {np.flatnonzero(~np.isfinite(actions).all(-1)).tolist()}"
        )
    return np.clip(actions, -1.0, 1.0)


RESET_OPTIONS = ("command",)
"""Keys `reset(options=...)` understands."""


def commands_from_options(options: dict | None, n: int, commands: Sequence[str] | CommandSpec) -> np.ndarray | None:
    """The commands (n, K) that `reset(options={"command": ...})` asks to hold, or None.

    A command is K numbers in the spec's order (ANYmal D: vx m/s, vy m/s, yaw rate rad/s); one command is given to every
    env, or one row per env. It holds for the whole episode (no resampling); a vector env keeps it through its
    auto-resets, and the next `reset()` without it samples commands again. `commands`: the spec's `CommandSpec` (or
    its names alone). Each number must be finite and, given the spec, within `command_limits`: a command past the
    range the spec samples is allowed (to probe how a policy extrapolates), one far past it is refused.
    """
    command_names = commands.names if isinstance(commands, CommandSpec) else tuple(commands)
    if not options:
        return None
    unknown = sorted(set(options) - set(RESET_OPTIONS))
    if unknown:
        raise ValueError(f"unknown reset option {unknown[0]!r}; known: {', '.join(RESET_OPTIONS)}")
    if "command" not in options or options["command"] is None:
        return None
    k = len(command_names)
    if k == 0:
        raise ValueError("this task has no commands: reset(options={'command': ...}) does not apply")
    try:
        command = np.asarray(options["command"], dtype=np.float32)
    except (TypeError, ValueError):
        raise ValueError(
            f"command must be {k} numbers ({', '.join(command_names)}), got {options['command']!r}"
        ) from None
    if command.shape == (k,):
        command = np.repeat(command[None], n, axis=0)
    if command.shape != (n, k) or not np.all(np.isfinite(command)):
        raise ValueError(
            f"command must be {k} finite numbers ({', '.join(command_names)}) or one row per env "
            f"({n}, {k}), got shape {command.shape}"
        )
    if isinstance(commands, CommandSpec):
        low, high = command_limits(commands)
        for i, name in enumerate(command_names):
            outside = command[:, i][(command[:, i] < low[i]) | (command[:, i] > high[i])]
            if outside.size:
                raise ValueError(
                    f"command {name} = {outside[0]:g} is far outside the spec's range [{commands.low[i]:g}, "
                    f"{commands.high[i]:g}]; reset(options={{'command': ...}}) takes [{low[i]:g}, {high[i]:g}]"
                )
    return command


def command_limits(commands: CommandSpec) -> tuple[np.ndarray, np.ndarray]:
    """The lowest and highest command `reset(options={"command": ...})` holds, per component: the spec's sampled
    range widened by its own width (at least 1 unit) on each side, e.g. vx in [-1, 1] m/s: [-3, 3] m/s."""
    low, high = np.asarray(commands.low, dtype=float), np.asarray(commands.high, dtype=float)
    width = np.maximum(high - low, 1.0)
    return low - width, high + width
