"""What an imagined env scores: the task behind the world model, chosen from the task spec.

`ImaginedCore` steps the model; a task turns its predictions into commands, reward and termination:

- `VelocityTrackingTask` (ANYmal D): velocity commands sampled at reset and on the spec's period, the legged reward
  of `rwm_gym.task.reward` with its feet-air-time timers, termination from the model's termination head;
- `SuiteRewardTask` (specs with a `[dm_control]` table): no commands, never terminates (suite tasks only hit their
  time limit), the suite's reward as a pure function of the predicted state, foot heights and the action
  (`rwm_gym.task.suite_reward`);
- `FunctionTask` (`rwm_gym.imagination.function_task`): either of the above, or no commands for a dm_control task,
  with reward and/or termination from functions of the predicted transition, named by the spec's `[imagination]`
  entry points or given as `reward_fn=` / `termination_fn=` (`rwm_gym.task.entry_points`).

Arrays are (N, ...) over the core's envs; `ids` index them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np

from rwm_gym.spec import TaskSpec
from rwm_gym.task.commands import resample_period, sample_commands
from rwm_gym.task.reward import FeetAirTime, reward_terms, total_reward


class ImaginedTask(Protocol):
    command: np.ndarray
    """(N, K) the current commands (K = 0 without commands)."""

    def reset(self, ids: np.ndarray, rngs: Sequence[np.random.Generator]) -> None:
        """New episodes in envs `ids`; `rngs` are their generators (one per id)."""

    def reward(self, next_state: np.ndarray, state: np.ndarray, contact: np.ndarray, foot_height: np.ndarray,
               action: np.ndarray, last_action: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Reward (N,) of the transition state --action--> next_state (SI units) and its named terms (each (N,))."""

    def terminated(self, termination_logit: np.ndarray) -> np.ndarray:
        """(N,) bool from the model's termination logits (N,)."""

    def advance(self, steps: np.ndarray, rngs: Sequence[np.random.Generator]) -> None:
        """After a step: `steps` (N,) policy steps since each env's reset."""


class VelocityTrackingTask:
    """Commands, legged reward and predicted termination of the velocity-tracking task (ANYmal D)."""

    def __init__(self, spec: TaskSpec, num_envs: int, resample_commands: bool = True):
        self.spec = spec
        self.command = np.zeros((num_envs, len(spec.command.names)), dtype=np.float32)
        self.air_time = FeetAirTime(num_envs, spec.foot_dim)
        self.period = resample_period(spec.command, spec.policy_dt) if resample_commands else np.iinfo(np.int64).max
        self._feet = np.isin(spec.privileged.contact_bodies, spec.privileged.feet)

    def reset(self, ids: np.ndarray, rngs: Sequence[np.random.Generator]) -> None:
        self.command[ids] = sample_commands(self.spec.command, list(rngs))
        self.air_time.reset(ids)

    def reward(self, next_state, state, contact, foot_height, action, last_action):
        air = self.air_time.update(contact[:, self._feet], self.spec.policy_dt, self.spec.reward.feet_air_time_target)
        terms = reward_terms(self.spec, next_state, state, contact, self.command, action, last_action, air)
        return total_reward(self.spec, terms), terms

    def terminated(self, termination_logit: np.ndarray) -> np.ndarray:
        return termination_logit > 0

    def advance(self, steps: np.ndarray, rngs: Sequence[np.random.Generator]) -> None:
        resample = np.flatnonzero(steps % self.period == 0)
        if len(resample):
            self.command[resample] = sample_commands(self.spec.command, [rngs[i] for i in resample])


class SuiteRewardTask:
    """A dm_control suite task: no commands, no termination, the suite's reward of the predicted state."""

    def __init__(self, spec: TaskSpec, num_envs: int):
        from rwm_gym.task.suite_reward import SuiteReward

        self.command = np.zeros((num_envs, 0), dtype=np.float32)
        self.suite_reward = SuiteReward(spec)

    def reset(self, ids: np.ndarray, rngs: Sequence[np.random.Generator]) -> None:
        pass

    def reward(self, next_state, state, contact, foot_height, action, last_action):
        return self.suite_reward(next_state, foot_height, action), {}

    def terminated(self, termination_logit: np.ndarray) -> np.ndarray:
        return np.zeros(len(termination_logit), dtype=bool)

    def advance(self, steps: np.ndarray, rngs: Sequence[np.random.Generator]) -> None:
        pass


def make_task(spec: TaskSpec, num_envs: int, *, resample_commands: bool = True, reward_fn=None,
              termination_fn=None) -> ImaginedTask:
    """The task of a spec: a dm_control suite task if it has a `[dm_control]` table, else velocity tracking; reward and
    termination functions (arguments, else the spec's entry points) replace theirs."""
    from rwm_gym.imagination.function_task import CommandlessTask, FunctionTask
    from rwm_gym.task.entry_points import step_functions

    reward_fn, termination_fn = step_functions(spec, reward_fn, termination_fn)
    if "dm_control" in spec.extra:
        base = SuiteRewardTask(spec, num_envs) if reward_fn is None else CommandlessTask(num_envs)
    else:
        base = VelocityTrackingTask(spec, num_envs, resample_commands)
    if reward_fn is None and termination_fn is None:
        return base
    return FunctionTask(spec, base, reward_fn, termination_fn)
