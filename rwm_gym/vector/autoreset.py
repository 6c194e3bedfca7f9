"""What the vector adapters share: Gymnasium's seeding convention and auto-reset in the same step.

Auto-reset (every adapter): an env that terminates or truncates is reset in the same call, and the observation returned
for it is the new episode's first; each adapter says where the last one goes. The core itself never resets on its own
(see `rwm_gym.batched_core`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from rwm_gym.batched_core import BatchedCore


def seeds_per_env(seed: int | Sequence[int | None] | None, n: int) -> list[int | None]:
    """Gymnasium's convention: an int seeds env i with seed + i; a list gives one seed per env."""
    if seed is None:
        return [None] * n
    if isinstance(seed, (int, np.integer)):
        return [int(seed) + i for i in range(n)]
    seeds = list(seed)
    if len(seeds) != n:
        raise ValueError(f"got {len(seeds)} seeds for {n} envs")
    return seeds


def step_with_autoreset(core: BatchedCore, actions: np.ndarray, held_commands: np.ndarray | None = None):
    """Step the core and reset finished envs (holding `held_commands` (N, K) if given); returns obs (new episodes'
    first where reset), reward, terminated, truncated, info, done ids and their final observations."""
    obs, reward, terminated, truncated, info = core.step(actions)
    done = np.flatnonzero(terminated | truncated)
    final_obs = obs[done].copy()
    if len(done):
        obs = obs.copy()
        obs[done] = core.reset(done, None, None if held_commands is None else held_commands[done])
    return obs, reward, terminated, truncated, info, done, final_obs
