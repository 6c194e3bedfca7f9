"""The task objects: commands, reward and termination of a task, one object shared by both simulators.

The physics core (`rwm_gym.physics.locomotion.LocomotionCore`) feeds a task measured states and contacts; the imagined
core (`rwm_gym.imagination.core.ImaginedCore`) feeds it the world model's predictions. Either way the same object
samples the commands, runs the feet-air-time timers and composes the reward, so the two cannot drift apart.

- `VelocityTrackingTask` (ANYmal D): velocity commands sampled at reset and on the spec's period, the legged reward of
  `rwm_gym.task.reward`; terminates (on the simulator's termination signal).
- `SuiteRewardTask` (specs with a `[dm_control]` table): no commands, never terminates (dm_control tasks only hit
  their time limit), the task's reward as a pure function of the state, foot heights and action
  (`rwm_gym.task.suite_reward`; a manipulation task's, and its success, from `rwm_gym.task.manipulation_reward`).
  The dm_control physics env scores with dm_control's own `get_reward` instead.
- `FunctionTask` (`rwm_gym.task.function_task`): either of the above, or no commands for a dm_control task, with
  reward and/or termination from functions of the transition, named by the spec's `[imagination]` entry points or
  given as `reward_fn=` / `termination_fn=` (`rwm_gym.task.entry_points`; the imagined env uses them).

Arrays are (N, ...) over the core's envs; `ids` index them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np

from rwm_gym.spec import TaskSpec
from rwm_gym.task.commands import resample_period, sample_commands
from rwm_gym.task.reward import FeetAirTime, reward_terms, total_reward


class Task(Protocol):
    """Commands, reward and termination of N envs, shared by the physics and the imagined cores."""

    command: np.ndarray
    """(N, K) the current commands (K = 0 without commands)."""
    terminates: bool
    """Whether the simulator's termination signal (a fall) ends an episode."""

    def reset(self, ids: np.ndarray, rngs: Sequence[np.random.Generator], commands: np.ndarray | None = None) -> None:
        """New episodes in envs `ids`; `rngs` are their generators (one per id). `commands` (len(ids), K): hold these
        for the episode instead of sampling."""

    def reward(
        self,
        next_state: np.ndarray,
        state: np.ndarray,
        contact: np.ndarray,
        foot_height: np.ndarray,
        action: np.ndarray,
        last_action: np.ndarray,
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Reward (N,) of the transition state --action--> next_state (SI units) and its named terms (each (N,)).
        Called once per step: it advances the task's timers."""

    def advance(self, steps: np.ndarray, rngs: Sequence[np.random.Generator]) -> None:
        """After a step: `steps` (N,) policy steps since each env's reset."""


class VelocityTrackingTask:
    """Commands and legged reward of the velocity-tracking task (ANYmal D).

    resample_commands: draw a new command every `command.resample_seconds` (off: one command per episode).
    """

    terminates = True

    def __init__(self, spec: TaskSpec, num_envs: int, resample_commands: bool = True):
        self.spec = spec
        self.resample_commands = resample_commands
        self.command = np.zeros((num_envs, len(spec.command.names)), dtype=np.float32)
        self.held = np.zeros(num_envs, dtype=bool)
        """(N,) envs whose command was given at reset and is not resampled."""
        self.air_time = FeetAirTime(num_envs, spec.foot_dim)
        self.period = resample_period(spec.command, spec.policy_dt)
        self._feet = np.isin(spec.privileged.contact_bodies, spec.privileged.feet)

    def reset(self, ids: np.ndarray, rngs: Sequence[np.random.Generator], commands: np.ndarray | None = None) -> None:
        # drawn even when a command is given, so that holding one leaves the rest of the episode's draws unchanged
        self.command[ids] = sample_commands(self.spec.command, list(rngs))
        if commands is not None:
            self.command[ids] = commands
        self.held[ids] = commands is not None
        self.air_time.reset(ids)

    def reward(self, next_state, state, contact, foot_height, action, last_action):
        air = self.air_time.update(contact[:, self._feet], self.spec.policy_dt, self.spec.reward.feet_air_time_target)
        terms = reward_terms(self.spec, next_state, state, contact, self.command, action, last_action, air)
        return total_reward(self.spec, terms), terms

    def advance(self, steps: np.ndarray, rngs: Sequence[np.random.Generator]) -> None:
        if not self.resample_commands:
            return
        resample = np.flatnonzero((steps % self.period == 0) & ~self.held)
        if len(resample):
            self.command[resample] = sample_commands(self.spec.command, [rngs[i] for i in resample])


def state_reward(spec: TaskSpec):
    """The reward of a dm_control spec as a function `(state, foot_height, action) -> (N,)`: a manipulation task's
    (`ManipulationReward`, which also judges success) or a suite task's (`SuiteReward`)."""
    from rwm_gym.task.dmc_environments import MANIPULATION

    if spec.extra.get("dm_control", {}).get("domain") == MANIPULATION:
        from rwm_gym.task.manipulation_reward import ManipulationReward

        return ManipulationReward(spec)
    from rwm_gym.task.suite_reward import SuiteReward

    return SuiteReward(spec)


class SuiteRewardTask:
    """A dm_control task: no commands, no termination, the task's reward of the state."""

    terminates = False

    def __init__(self, spec: TaskSpec, num_envs: int):
        self.command = np.zeros((num_envs, 0), dtype=np.float32)
        self.suite_reward = state_reward(spec)
        self.held_columns: tuple[int, ...] = getattr(self.suite_reward, "held_columns", ())
        """State columns the imagined env holds through an episode (a reach's target; `ManipulationReward`)."""
        self.success: np.ndarray | None = None
        """(N,) bool after each reward: the manipulation goal met at that step (None for suite tasks)."""

    def reset(self, ids: np.ndarray, rngs: Sequence[np.random.Generator], commands: np.ndarray | None = None) -> None:
        if commands is not None and commands.shape[-1]:
            raise ValueError("a dm_control suite task has no commands")

    def reward(self, next_state, state, contact, foot_height, action, last_action):
        reward = self.suite_reward(next_state, foot_height, action)
        if hasattr(self.suite_reward, "success"):
            self.success = reward >= self.suite_reward.success_reward
        return reward, {}

    def advance(self, steps: np.ndarray, rngs: Sequence[np.random.Generator]) -> None:
        pass


def make_task(
    spec: TaskSpec,
    num_envs: int,
    *,
    resample_commands: bool = True,
    reward_fn=None,
    termination_fn=None,
    trust_entry_points: bool = False,
    source: str = "the task spec",
) -> Task:
    """The task of a spec: a dm_control suite task if it has a `[dm_control]` table, else velocity tracking; reward and
    termination functions (arguments, else the spec's entry points if trusted) replace theirs."""
    from rwm_gym.task.entry_points import step_functions
    from rwm_gym.task.function_task import CommandlessTask, FunctionTask

    reward_fn, termination_fn = step_functions(spec, reward_fn, termination_fn, trust=trust_entry_points, source=source)
    if "dm_control" in spec.extra:
        base = SuiteRewardTask(spec, num_envs) if reward_fn is None else CommandlessTask(num_envs)
    else:
        base = VelocityTrackingTask(spec, num_envs, resample_commands)
    if reward_fn is None and termination_fn is None:
        return base
    return FunctionTask(spec, base, reward_fn, termination_fn)
