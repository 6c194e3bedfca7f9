"""Batched environments behind the two vector APIs our users plug into: Gymnasium's `VectorEnv` and SB3's `VecEnv`.

Any *core* that steps N envs at once (the MuJoCo batch, the world model) is wrapped here, so both APIs share one tested
auto-reset rule. A core provides:

- `num_envs`, `single_observation_space`, `single_action_space`, `spec` (the TaskSpec);
- `reset(ids, seeds) -> obs`: start new episodes in envs `ids` (array), seeding those whose seed is not None;
  returns their observations, shape (len(ids), obs_dim);
- `step(actions) -> obs, reward, terminated, truncated, info`: every env one step, arrays with a leading N axis and
  `info` a dict of (N, ...) arrays; the core never resets on its own.

Auto-reset: an env that terminates or truncates is reset in the same call. Gymnasium (`AutoresetMode.SAME_STEP`): the
returned observation is the new episode's first; the last one is `info["final_obs"]` (mask `info["_final_obs"]`).
SB3: the last observation is `infos[i]["terminal_observation"]`, truncation is `infos[i]["TimeLimit.truncated"]`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space
from stable_baselines3.common.vec_env.base_vec_env import VecEnv


class BatchedCore(Protocol):
    num_envs: int
    single_observation_space: gym.spaces.Box
    single_action_space: gym.spaces.Box

    def reset(self, ids: np.ndarray, seeds: Sequence[int | None] | None = None) -> np.ndarray: ...

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]: ...


def _seeds(seed: int | Sequence[int | None] | None, n: int) -> list[int | None]:
    """Gymnasium's convention: an int seeds env i with seed + i; a list gives one seed per env."""
    if seed is None:
        return [None] * n
    if isinstance(seed, (int, np.integer)):
        return [int(seed) + i for i in range(n)]
    seeds = list(seed)
    if len(seeds) != n:
        raise ValueError(f"got {len(seeds)} seeds for {n} envs")
    return seeds


def step_with_autoreset(core: BatchedCore, actions: np.ndarray):
    """Step the core and reset finished envs; returns obs (new episodes' first where reset), reward, terminated,
    truncated, info, done ids and their final observations."""
    obs, reward, terminated, truncated, info = core.step(actions)
    done = np.flatnonzero(terminated | truncated)
    final_obs = obs[done].copy()
    if len(done):
        obs = obs.copy()
        obs[done] = core.reset(done)
    return obs, reward, terminated, truncated, info, done, final_obs


class CoreVectorEnv(gym.vector.VectorEnv):
    """Gymnasium `VectorEnv` over a batched core (same-step auto-reset)."""

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(self, core: BatchedCore):
        self.core = core
        self.num_envs = core.num_envs
        self.single_observation_space = core.single_observation_space
        self.single_action_space = core.single_action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)

    def reset(self, *, seed: int | Sequence[int | None] | None = None, options: dict | None = None):
        super().reset(seed=seed if isinstance(seed, (int, type(None))) else None)
        obs = self.core.reset(np.arange(self.num_envs), _seeds(seed, self.num_envs))
        return obs, {}

    def step(self, actions):
        obs, reward, terminated, truncated, info, done, final_obs = step_with_autoreset(self.core, actions)
        infos: dict[str, Any] = dict(info)
        if len(done):
            mask = np.zeros(self.num_envs, dtype=bool)
            mask[done] = True
            full = np.zeros_like(obs)
            full[done] = final_obs
            infos["final_obs"], infos["_final_obs"] = full, mask
        return obs, reward, terminated, truncated, infos


class CoreVecEnv(VecEnv):
    """Stable-Baselines3 `VecEnv` over a batched core (numpy in and out, SB3's auto-reset rules)."""

    def __init__(self, core: BatchedCore):
        self.core = core
        if not hasattr(core, "render_mode"):
            core.render_mode = None  # batched cores do not render; SB3 asks every env for this attribute
        super().__init__(core.num_envs, core.single_observation_space, core.single_action_space)
        self._actions: np.ndarray | None = None
        self._seeds: list[int | None] = [None] * core.num_envs

    def seed(self, seed: int | None = None) -> Sequence[None | int]:
        self._seeds = _seeds(seed, self.num_envs)
        return self._seeds

    def reset(self) -> np.ndarray:
        obs = self.core.reset(np.arange(self.num_envs), self._seeds)
        self._seeds = [None] * self.num_envs
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions)

    def step_wait(self):
        obs, reward, terminated, truncated, info, done, final_obs = step_with_autoreset(self.core, self._actions)
        infos = [{k: v[i] for k, v in info.items()} for i in range(self.num_envs)]
        for row, i in enumerate(done):
            infos[i]["terminal_observation"] = final_obs[row]
            infos[i]["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
        return obs, reward.astype(np.float32), terminated | truncated, infos

    def close(self) -> None:
        pass

    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        return [getattr(self.core, attr_name)] * len(self._indices(indices))

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        setattr(self.core, attr_name, value)

    def env_method(self, method_name: str, *args, indices=None, **kwargs) -> list[Any]:
        return [getattr(self.core, method_name)(*args, **kwargs) for _ in self._indices(indices)]

    def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
        return [False] * len(self._indices(indices))

    def _indices(self, indices) -> list[int]:
        if indices is None:
            return list(range(self.num_envs))
        return [indices] if isinstance(indices, int) else list(indices)
