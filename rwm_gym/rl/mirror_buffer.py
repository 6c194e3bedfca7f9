"""PPO's rollout buffer with left-right mirror augmentation (`PPOConfig.symmetry`).

Every minibatch carries each sample and, after it, its mirror image (`rwm_gym.task.symmetry`): mirrored observation
and action, the same advantage, return, old value and old log-probability. The mirrored samples are what the rollout
policy's mirror image would have done, so the original's old log-probability is theirs (as in rsl_rl's symmetric
PPO): PPO's ratio on the mirrored half compares the policy with that mirror image, stays bounded by the policy's own
densities, and the update pulls an asymmetric policy towards the mirror of its own behaviour. (The rollout policy's
own log-probability of the mirrored action has no such bound: where the policy has grown asymmetric the ratio can
overflow, and a loop from random data with it, its learning rate no longer cut, ended in a NaN policy in its first
iteration.) The number of minibatches stays the same; each one doubles. The policy learns from twice the data for the
same number of (imagined) steps, and is pushed towards the symmetric gaits a left-right symmetric robot can use.

SB3 normalises advantages per minibatch; a minibatch of n samples and their copies has the same mean and a standard
deviation smaller by sqrt((2n - 2) / (2n - 1)) (1 - 1e-4 at n = 3072), which is left as it is.
The KL that adapts the learning rate (`original_kl`) is measured on the original half only, as rsl_rl's is: on the
mirrored half an asymmetric policy starts far from its mirror image, and a KL over both halves drove the adaptive
rate to its floor within three iterations of a loop from random data. SB3's logged `train/approx_kl` covers both.

The buffer is installed on a built model (`use_mirrored_buffer`), not through SB3's `rollout_buffer_class`, so saved
policies carry no reference to it and load anywhere.
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

    def __init__(
        self,
        buffer_size: int,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        device: torch.device | str = "auto",
        gae_lambda: float = 1,
        gamma: float = 0.99,
        n_envs: int = 1,
        *,
        observation_mirror: Mirror,
        action_mirror: Mirror,
        policy: torch.nn.Module,
    ):
        super().__init__(buffer_size, observation_space, action_space, device, gae_lambda, gamma, n_envs)
        self.policy = policy
        if observation_mirror.index.shape != observation_space.shape or action_mirror.index.shape != action_space.shape:
            raise ValueError(
                f"mirror of {observation_mirror.index.shape} observations and {action_mirror.index.shape} "
                f"actions for spaces of shape {observation_space.shape} and {action_space.shape}"
            )
        self.mirrors = tuple(
            (
                torch.as_tensor(m.index, device=self.device),
                torch.as_tensor(m.sign, dtype=torch.float32, device=self.device),
            )
            for m in (observation_mirror, action_mirror)
        )

    def get(self, batch_size: int | None = None):
        if not self.generator_ready:  # a new update: its first epoch
            self.kls: list[float] = []
        yield from super().get(batch_size)

    @property
    def original_kl(self) -> float | None:
        """The last update's mean approximate KL over its minibatches' original halves (None before any update)."""
        kls = getattr(self, "kls", None)
        return float(np.mean(kls)) if kls else None

    def _get_samples(self, batch_inds: np.ndarray, env: VecNormalize | None = None) -> RolloutBufferSamples:
        samples = super()._get_samples(batch_inds, env)
        with torch.no_grad():  # SB3's approximate KL, on the original half, by the policy before this minibatch's step
            log_prob = self.policy.get_distribution(samples.observations).log_prob(samples.actions)  # no critic
            log_ratio = log_prob - samples.old_log_prob
            self.kls.append(float(torch.mean(torch.exp(log_ratio) - 1 - log_ratio)))
        (obs_index, obs_sign), (act_index, act_sign) = self.mirrors
        return RolloutBufferSamples(
            observations=torch.cat([samples.observations, samples.observations[:, obs_index] * obs_sign]),
            actions=torch.cat([samples.actions, samples.actions[:, act_index] * act_sign]),
            old_values=samples.old_values.repeat(2),
            old_log_prob=samples.old_log_prob.repeat(2),
            advantages=samples.advantages.repeat(2),
            returns=samples.returns.repeat(2),
        )


def use_mirrored_buffer(model, spec: TaskSpec) -> None:
    """Give the SB3 PPO `model` a `MirroredRolloutBuffer` for the task of `spec` (after building or loading it).

    ValueError (one line) when the spec has no `[symmetry]` table.
    """
    old = model.rollout_buffer
    model.rollout_buffer = MirroredRolloutBuffer(
        old.buffer_size,
        old.observation_space,
        old.action_space,
        old.device,
        old.gae_lambda,
        old.gamma,
        old.n_envs,
        observation_mirror=observation_mirror(spec),
        action_mirror=action_mirror(spec),
        policy=model.policy,
    )
