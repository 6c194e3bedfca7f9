"""`RWM-AnymalD-v0`, `RWM-Cheetah-v0`, ...: a `gymnasium.Env` whose step queries the world model instead of physics.

Same observation and action spaces, commands, reward and termination as the task's physics env (`AnymalD-MuJoCo-v0`,
`DMC-Cheetah-Run-v0`, ...; one task object of `rwm_gym.task.tasks` serves both). `render_mode="rgb_array"` (tasks with
their own MJCF
model, i.e. ANYmal D) draws the dream: predicted joint angles and base attitude set into the MuJoCo model, the base
position integrated from the predicted velocity.

`ImaginedEnv` is the imagined core with N = 1; the vector envs of `rwm_gym.vector` are the same core with N > 1
(`make_imagined_core`).
"""

from __future__ import annotations

import atexit
from dataclasses import fields, replace
from pathlib import Path

import gymnasium as gym
import numpy as np

from rwm_gym.batched_core import commands_from_options
from rwm_gym.imagination.core import ImaginationOptions, ImaginedCore


def imagination_options(options: ImaginationOptions | None = None, **fields) -> ImaginationOptions:
    """`options` (default `ImaginationOptions()`) with the named fields replaced: the one place where keyword
    conveniences (`gym.make("RWM-AnymalD-v0", fall_tilt=30)`) become the options object."""
    return replace(options or ImaginationOptions(), **fields)


def make_imagined_core(
    checkpoint: str | Path | None = None, num_envs: int = 1, *, options: ImaginationOptions | None = None, **kwargs
) -> ImaginedCore:
    """The imagined core of N rollouts. kwargs: `ImaginedCore`'s (device, reset_data, env_id, reward_fn,
    termination_fn), and fields of `ImaginationOptions` that replace those of `options`."""
    names = {f.name for f in fields(ImaginationOptions)}
    given = {k: kwargs.pop(k) for k in [k for k in kwargs if k in names]}
    return ImaginedCore(checkpoint, num_envs, options=imagination_options(options, **given), **kwargs)


class ImaginedEnv(gym.Env):
    """One imagined rollout. kwargs as `make_imagined_core`: device, reset_data, env_id, reward_fn, termination_fn,
    `options` (an `ImaginationOptions`) and its fields one by one (sample_predictions, uncertainty_penalty,
    resample_commands, ...). `reset(options={"command": (vx, vy, yaw_rate)})` holds a command for the episode.

    reward_fn / termination_fn: functions of the predicted `rwm_gym.task.entry_points.Transition` returning (N,)
    rewards / bools, replacing the task's (default: the spec's `[imagination]` entry points, else the task's own).
    """

    metadata = {"render_modes": ["rgb_array"]}  # render_fps: the spec's control rate, set per instance

    def __init__(
        self,
        checkpoint: str | Path | None = None,
        *,
        render_mode: str | None = None,
        width: int = 640,
        height: int = 480,
        **kwargs,
    ):
        self.core = make_imagined_core(checkpoint, 1, **kwargs)
        self.task_spec = self.core.spec
        if render_mode is not None and not self.task_spec.model:
            raise ValueError(
                f"{self.core.checkpoint}: {self.task_spec.name} has no MJCF model of its own to draw the "
                "dream with; render its physics env instead"
            )
        self.observation_space = self.core.single_observation_space
        self.action_space = self.core.single_action_space
        self.metadata = {**self.metadata, "render_fps": int(round(1.0 / self.task_spec.policy_dt))}
        self.render_mode = render_mode
        self._render_size = (height, width)
        self._dream = None

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        commands = commands_from_options(options, 1, self.task_spec.command)
        obs = self.core.reset(np.array([0]), [seed], commands)
        if self._dream is not None:
            self._dream.reset()
        return obs[0], {"command": self.core.command[0].copy()}

    def step(self, action):
        obs, reward, terminated, truncated, info = self.core.step(np.asarray(action)[None])
        if self._dream is not None:
            self._dream.advance(self.core.state[0], self.core.foot_height[0])
        return obs[0], float(reward[0]), bool(terminated[0]), bool(truncated[0]), {k: v[0] for k, v in info.items()}

    def render(self):
        if self.render_mode != "rgb_array":
            return None
        if self._dream is None:
            from rwm_gym.imagination.dream import DreamRenderer

            self._dream = DreamRenderer(self.task_spec, *self._render_size)
            atexit.register(self.close)  # an env left open at exit closes before EGL is torn down (no traceback)
            self._dream.advance(self.core.state[0], self.core.foot_height[0], dt=0.0)
        return self._dream.render()

    def close(self):
        if self._dream is not None:
            atexit.unregister(self.close)
            self._dream.close()
            self._dream = None
