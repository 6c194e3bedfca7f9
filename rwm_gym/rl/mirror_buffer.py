"""PPO's rollout buffer with left-right mirror augmentation (`PPOConfig.symmetry`).

Every minibatch carries each sample and, after it, its mirror image (`rwm_gym.task.symmetry`): mirrored observation
and action, the same advantage, return and old value, and the original's old log-probability, as a symmetric policy
would give the mirrored action the same probability in the mirrored state. The number of minibatches stays the same;
each one doubles. The policy learns from twice the data for the same number of (imagined) steps, and is pushed
towards the symmetric gaits a left-right symmetric robot can use.

SB3 normalises advantages per minibatch; a minibatch of n samples and their copies has the same mean and a standard
deviation smaller by sqrt((2n - 2) / (2n - 1)) (1 - 1e-4 at n = 3072), which is left as it is.
SB3's `train/approx_kl` (and so the adaptive learning rate) is measured over both halves.
"""

from __future__ import annotations

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3.common.buffers import RolloutBuffer
from stable_baselines3.common.type_aliases import RolloutBufferSamples
from stable_baselines3.common.vec_env import VecNormalize

from rwm_gym.spec import TaskSpec
from rwm_gym.task.symmetry import Mirror, action_mirror, observation_mirror


class MirroredRolloutBuffer(RolloutBuffer):
    """SB3 `RolloutBuffer` whose minibatches are [samples; their mirror images], shape (2 x batch_size, ...).

    `observation_mirror` and `action_mirror` map an observation (O,) and an action (A,) to their mirror images.
    """

    def __init__(self, buffer_size: int, observation_space: spaces.Space, action_space: spaces.Space,
                 device: torch.device | str = "auto", gae_lambda: float = 1, gamma: float = 0.99, n_envs: int = 1, *,
                 observation_mirror: Mirror, action_mirror: Mirror):
        super().__init__(buffer_size, observation_space, action_space, device, gae_lambda, gamma, n_envs)
        if observation_mirror.index.shape != observation_space.shape or action_mirror.index.shape != action_space.shape:
            raise ValueError(f"mirror of {observation_mirror.index.shape} observations and {action_mirror.index.shape} "
                             f"actions for spaces of shape {observation_space.shape} and {action_space.shape}")
        self.mirrors = tuple((torch.as_tensor(m.index, device=self.device),
                              torch.as_tensor(m.sign, dtype=torch.float32, device=self.device))
                             for m in (observation_mirror, action_mirror))

    def _get_samples(self, batch_inds: np.ndarray, env: VecNormalize | None = None) -> RolloutBufferSamples:
        samples = super()._get_samples(batch_inds, env)
        (obs_index, obs_sign), (act_index, act_sign) = self.mirrors
        return RolloutBufferSamples(
            observations=torch.cat([samples.observations, samples.observations[:, obs_index] * obs_sign]),
            actions=torch.cat([samples.actions, samples.actions[:, act_index] * act_sign]),
            old_values=samples.old_values.repeat(2),
            old_log_prob=samples.old_log_prob.repeat(2),
            advantages=samples.advantages.repeat(2),
            returns=samples.returns.repeat(2),
        )


def mirrored_buffer_options(spec: TaskSpec) -> dict:
    """`PPO(**options)` that make its rollout buffer a `MirroredRolloutBuffer` for the task of `spec`.

    ValueError (one line) when the spec has no `[symmetry]` table.
    """
    return {"rollout_buffer_class": MirroredRolloutBuffer,
            "rollout_buffer_kwargs": {"observation_mirror": observation_mirror(spec),
                                      "action_mirror": action_mirror(spec)}}
