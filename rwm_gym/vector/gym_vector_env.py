"""A batched core as a Gymnasium `VectorEnv` (Gymnasium 1.x conventions).

Auto-reset is `AutoresetMode.SAME_STEP`: the observation returned for a finished env is its new episode's first; the
last one is `info["final_obs"]` (N, O), valid where the mask `info["_final_obs"]` is True. Every info key `k` comes with
its mask `info["_k"]`, as `SyncVectorEnv` gives them. `reset(options={"command": (vx, vy, yaw)})` holds a command (see
`rwm_gym.batched_core.commands_from_options`).

The envs of each core are here too (`gym.make_vec(id, num_envs=N, vectorization_mode="vector_entry_point")` makes
them): MuJoCo physics, dm_control physics, imagination. Each imports its core when made, so that a physics user does
not import torch, and no user imports Stable-Baselines3.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space

from rwm_gym.batched_core import BatchedCore, commands_from_options
from rwm_gym.spec import TaskSpec
from rwm_gym.vector.autoreset import seeds_per_env, step_with_autoreset


class CoreGymVectorEnv(gym.vector.VectorEnv):
    """Gymnasium `VectorEnv` over a batched core (same-step auto-reset)."""

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(self, core: BatchedCore):
        self.core = core
        self.num_envs = core.num_envs
        self.single_observation_space = core.single_observation_space
        self.single_action_space = core.single_action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._held_commands: np.ndarray | None = None
        self._needs_reset = True

    def reset(self, *, seed: int | Sequence[int | None] | None = None, options: dict | None = None):
        super().reset(seed=seed if isinstance(seed, (int, type(None))) else None)
        self._held_commands = commands_from_options(options, self.num_envs, self.core.spec.command)
        obs = self.core.reset(np.arange(self.num_envs), seeds_per_env(seed, self.num_envs), self._held_commands)
        self._needs_reset = False
        return obs, {}

    def step(self, actions):
        if self._needs_reset:
            raise gym.error.ResetNeeded("call reset() before step()")
        obs, reward, terminated, truncated, info, done, final_obs = step_with_autoreset(
            self.core, actions, self._held_commands
        )
        every = np.ones(self.num_envs, dtype=bool)
        infos: dict[str, Any] = {}
        for key, value in info.items():
            infos[key], infos[f"_{key}"] = value, every
        if len(done):
            mask = np.zeros(self.num_envs, dtype=bool)
            mask[done] = True
            full = np.zeros_like(obs)
            full[done] = final_obs
            infos["final_obs"], infos["_final_obs"] = full, mask
        return obs, reward, terminated, truncated, infos


class LocomotionGymVectorEnv(CoreGymVectorEnv):
    """Gymnasium VectorEnv of N MuJoCo simulations (`mujoco.batch` on a thread pool); kwargs as `make_core`:
    `options` (a `PhysicsOptions`) and its fields (`nthread`: threads of the pool, 0 all CPUs)."""

    def __init__(self, num_envs: int = 1, spec: str | TaskSpec = "anymal_d", **kwargs):
        from rwm_gym.physics.locomotion import make_core

        kwargs.pop("render_mode", None)
        super().__init__(make_core(spec, num_envs, **kwargs))


class DMCGymVectorEnv(CoreGymVectorEnv):
    """Gymnasium VectorEnv of N copies of a dm_control task (`gym.make_vec(id, num_envs=N)`)."""

    def __init__(self, num_envs: int = 1, spec: str | TaskSpec = "dmc_cheetah_run", **kwargs):
        from rwm_gym.physics.dmc import make_core

        kwargs.pop("render_mode", None)
        super().__init__(make_core(spec, num_envs, **kwargs))


class ImaginedGymVectorEnv(CoreGymVectorEnv):
    """Gymnasium VectorEnv of N imagined rollouts, all in one forward pass of the world model; kwargs as
    `ImaginedEnv`. Every reset replays a real warm-up."""

    def __init__(self, num_envs: int = 1, checkpoint: str | Path | None = None, **kwargs):
        from rwm_gym.imagination.env import make_imagined_core

        kwargs.pop("render_mode", None)
        super().__init__(make_imagined_core(checkpoint, num_envs, **kwargs))
