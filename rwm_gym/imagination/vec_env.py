"""The imagined env, batched: all N rollouts in one forward pass of the world model.

`gym.make_vec("RWM-AnymalD-v0", num_envs=N, vectorization_mode="vector_entry_point")` (or any `RWM-*` id) gives
`ImaginedGymVectorEnv`; SB3 takes `ImaginedSB3VecEnv`. Both share the auto-reset rules of `rwm_gym.vector`; every
reset replays a real warm-up.
"""

from __future__ import annotations

from pathlib import Path

from rwm_gym.imagination.core import ImaginationOptions, ImaginedCore
from rwm_gym.vector.gym_vector_env import CoreGymVectorEnv
from rwm_gym.vector.sb3_vec_env import CoreSB3VecEnv


def make_imagined_core(checkpoint: str | Path | None = None, num_envs: int = 1, *, device: str = "cpu",
                       reset_data: str | Path | None = None, env_id: str | None = None, **options) -> ImaginedCore:
    return ImaginedCore(checkpoint, num_envs, device=device, reset_data=reset_data,
                        options=ImaginationOptions(**options), env_id=env_id)


class ImaginedGymVectorEnv(CoreGymVectorEnv):
    """Gymnasium VectorEnv of N imagined rollouts; kwargs as `ImaginedEnv`."""

    def __init__(self, num_envs: int = 1, checkpoint: str | Path | None = None, **kwargs):
        kwargs.pop("render_mode", None)
        super().__init__(make_imagined_core(checkpoint, num_envs, **kwargs))


class ImaginedSB3VecEnv(CoreSB3VecEnv):
    """Stable-Baselines3 VecEnv of N imagined rollouts (numpy in and out; the model on cpu or cuda)."""

    def __init__(self, checkpoint: str | Path | None = None, num_envs: int = 1, **kwargs):
        super().__init__(make_imagined_core(checkpoint, num_envs, **kwargs))


ImaginedVectorEnv, ImaginedVecEnv = ImaginedGymVectorEnv, ImaginedSB3VecEnv  # deprecated names
