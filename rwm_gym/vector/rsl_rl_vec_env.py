"""A batched core as rsl_rl's `VecEnv` (the `rsl-rl-lib` package: `pip install "rwm-gym[rsl-rl]"`).

rsl_rl is the PPO that legged-robot policies (and RWM's) are trained with, on Isaac Lab envs. Its `OnPolicyRunner`
assumes Isaac Lab's conventions, which this adapter follows, so the runner trains in imagination (or in MuJoCo)
unchanged:

- torch tensors on `device`; observations a `TensorDict` with one group, "policy" (num_envs, O), which rsl_rl's
  default `obs_groups` feed to the actor and the critic alike;
- `step(actions)` -> obs, rewards (num_envs,) float32, dones (num_envs,) long, extras; actions outside [-1, 1] are
  clipped by the core (rsl_rl samples an unbounded Gaussian);
- auto-reset in the same step: a finished env's returned observation is its new episode's first (rsl_rl never reads
  the last one: it bootstraps a time-out with the value of the state the step started from);
- extras["time_outs"] (num_envs,) bool: episodes cut by the time limit, not terminated (PPO bootstraps them);
- extras["log"]: on steps where episodes end, the mean over those episodes of each reward term's sum, the raw term
  before its weight and dt ("Episode_Term/<term>", the core's info["reward/<term>"]), and the share that timed out,
  terminated or (imagination) saw the model diverge ("Episode_Termination/<why>"); the runner writes them to
  TensorBoard and prints them;
- `episode_length_buf` is the core's own step counter (a view on CPU): writing it, as
  `OnPolicyRunner.learn(init_at_random_ep_len=True)` does, moves every env's time limit, as in Isaac Lab.

This module and `rwm_gym.rl.rsl_rl_runner` (its runner on several processes or GPUs) are the only ones that import
rsl_rl, so the rest of rwm-gym runs without it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, is_dataclass
from pathlib import Path

import numpy as np
import torch
from rsl_rl.env import VecEnv
from tensordict import TensorDict

from rwm_gym.batched_core import BatchedCore, commands_from_options
from rwm_gym.vector.autoreset import seeds_per_env, step_with_autoreset

OBSERVATION_GROUP = "policy"
"""The one observation group: Isaac Lab's name, which rsl_rl falls back to for every observation set."""


@dataclass(frozen=True)
class RslRlEnvConfig:
    """What the runner logs as the env's config (`env.cfg`; W&B stores it through `to_dict`)."""

    task: str
    """The task spec's name."""
    num_envs: int
    episode_steps: int
    """Time limit in policy steps."""
    policy_dt: float
    """Seconds per policy step."""
    options: dict = field(default_factory=dict)
    """The core's options (the imagined env's `ImaginationOptions`; empty for physics)."""

    def to_dict(self) -> dict:
        return asdict(self)


def episode_steps(core: BatchedCore) -> int:
    """The core's time limit in policy steps (the imagined core may override the spec's)."""
    return int(getattr(core, "episode_steps", None) or core.spec.episode_steps)


class CoreRslRlVecEnv(VecEnv):
    """rsl_rl `VecEnv` over a batched core (torch in and out, Isaac Lab's auto-reset and time-out rules).

    The envs are reset on construction (`seed`: env i gets seed + i; None: fresh entropy), so
    `get_observations()` is ready for `OnPolicyRunner(env, ...)`.
    """

    def __init__(self, core: BatchedCore, *, seed: int | None = 0, device: str | torch.device | None = None):
        self.core = core
        self.num_envs: int = core.num_envs
        self.num_actions: int = int(core.single_action_space.shape[0])
        self.max_episode_length: int = episode_steps(core)
        self.device = torch.device(device if device is not None else getattr(core, "device", "cpu"))
        options = getattr(core, "options", None)
        self.cfg = RslRlEnvConfig(
            task=core.spec.name,
            num_envs=self.num_envs,
            episode_steps=self.max_episode_length,
            policy_dt=float(core.spec.policy_dt),
            options=asdict(options) if is_dataclass(options) else {},
        )
        self._held_commands: np.ndarray | None = None
        self._term_sums: dict[str, np.ndarray] = {}
        self._obs = self.reset(seed=seed)

    @property
    def episode_length_buf(self) -> torch.Tensor:
        """Policy steps taken in each env's current episode. Shape: (num_envs,), int64."""
        steps = torch.from_numpy(self.core.steps)  # shares memory with the core
        return steps if self.device.type == "cpu" else steps.to(self.device)

    @episode_length_buf.setter
    def episode_length_buf(self, value: torch.Tensor) -> None:
        value = torch.as_tensor(value).reshape(-1)
        if value.shape != (self.num_envs,):
            raise ValueError(f"episode_length_buf must have shape ({self.num_envs},), got {tuple(value.shape)}")
        self.core.steps[:] = value.to("cpu", torch.int64).numpy()

    def reset(self, seed: int | None = None, command=None) -> TensorDict:
        """Start a new episode in every env; `command` (K numbers, or one row per env) is held through auto-resets
        until the next reset without it (see `rwm_gym.batched_core.commands_from_options`)."""
        commands = self.core.spec.command
        self._held_commands = commands_from_options({"command": command}, self.num_envs, commands)
        obs = self.core.reset(np.arange(self.num_envs), seeds_per_env(seed, self.num_envs), self._held_commands)
        self._term_sums = {}
        self._obs = self._observations(obs)
        return self._obs

    def get_observations(self) -> TensorDict:
        return self._obs

    def step(self, actions: torch.Tensor) -> tuple[TensorDict, torch.Tensor, torch.Tensor, dict]:
        """Every env one step. actions: (num_envs, num_actions). Returns obs, rewards (num_envs,), dones (num_envs,)
        and extras with "time_outs" (num_envs,) and, when episodes ended, "log"."""
        actions_np = actions.detach().to("cpu", torch.float64).numpy()
        obs, reward, terminated, truncated, info, done, _ = step_with_autoreset(
            self.core, actions_np, self._held_commands
        )
        self._obs = self._observations(obs)
        time_outs = truncated & ~terminated
        extras: dict = {"time_outs": torch.as_tensor(time_outs, device=self.device)}
        log = self._episode_log(info, done, terminated, time_outs)
        if log:
            extras["log"] = log
        rewards = torch.as_tensor(np.asarray(reward, dtype=np.float32), device=self.device)
        dones = torch.as_tensor((terminated | truncated).astype(np.int64), device=self.device)
        return self._obs, rewards, dones, extras

    def close(self) -> None:
        pass

    def _observations(self, obs: np.ndarray) -> TensorDict:
        policy = torch.as_tensor(np.asarray(obs, dtype=np.float32), device=self.device)
        return TensorDict({OBSERVATION_GROUP: policy}, batch_size=[self.num_envs], device=self.device)

    def _episode_log(
        self, info: dict, done: np.ndarray, terminated: np.ndarray, time_outs: np.ndarray
    ) -> dict[str, float]:
        """Accumulate each reward term per env; for the envs in `done`, the means over their episodes."""
        log: dict[str, float] = {}
        for key, value in info.items():
            if not key.startswith("reward/"):
                continue
            sums = self._term_sums.setdefault(key, np.zeros(self.num_envs))
            sums += value
            if len(done):
                log[f"Episode_Term/{key[len('reward/') :]}"] = float(sums[done].mean())
                sums[done] = 0.0
        if len(done):
            log["Episode_Termination/time_out"] = float(time_outs[done].mean())
            log["Episode_Termination/terminated"] = float(terminated[done].mean())
            if "model_diverged" in info:
                log["Episode_Termination/model_diverged"] = float(np.asarray(info["model_diverged"])[done].mean())
        return log


class ImaginedRslRlVecEnv(CoreRslRlVecEnv):
    """rsl_rl VecEnv of N imagined rollouts; kwargs as `ImaginedSB3VecEnv` (the model on cpu or cuda, and there the
    tensors too)."""

    def __init__(self, checkpoint: str | Path | None = None, num_envs: int = 1, *, seed: int | None = 0, **kwargs):
        from rwm_gym.imagination.env import make_imagined_core

        super().__init__(make_imagined_core(checkpoint, num_envs, **kwargs), seed=seed)


class LocomotionRslRlVecEnv(CoreRslRlVecEnv):
    """rsl_rl VecEnv of N MuJoCo simulations (the physics that judges policies); kwargs as `LocomotionSB3VecEnv`.
    `device` is where the tensors go (the simulation runs on the CPU)."""

    def __init__(
        self,
        num_envs: int = 1,
        spec: str = "anymal_d",
        *,
        seed: int | None = 0,
        device: str | torch.device = "cpu",
        **kwargs,
    ):
        from rwm_gym.physics.locomotion import make_core

        super().__init__(make_core(spec, num_envs, **kwargs), seed=seed, device=device)
