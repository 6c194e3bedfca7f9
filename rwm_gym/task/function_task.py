"""A task whose reward and/or termination are functions of the transition (`rwm_gym.task.entry_points`).

Built by `rwm_gym.task.tasks.make_task` when a spec names entry points (`[imagination] reward = "m:f"`) or the
imagined env gets `reward_fn=` / `termination_fn=`. It keeps the commands of the task underneath (velocity commands
for a legged robot, none for a dm_control task) and replaces what was given.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from rwm_gym.spec import TaskSpec
from rwm_gym.task.entry_points import StepFunction, Transition, call


class CommandlessTask:
    """No commands, no reward of its own, never terminates: the base of a dm_control task with a reward function."""

    terminates = False

    def __init__(self, num_envs: int):
        self.command = np.zeros((num_envs, 0), dtype=np.float32)

    def reset(self, ids: np.ndarray, rngs: Sequence[np.random.Generator], commands: np.ndarray | None = None) -> None:
        if commands is not None and commands.shape[-1]:
            raise ValueError("this task has no commands")

    def reward(self, next_state, state, contact, foot_height, action, last_action):
        raise NotImplementedError("CommandlessTask has no reward: give a reward function")

    def advance(self, steps: np.ndarray, rngs: Sequence[np.random.Generator]) -> None:
        pass


class FunctionTask:
    """`base`'s commands; reward and termination from the given functions where given, else `base`'s.

    A termination function replaces the simulator's termination signal (`terminates` is then False); its verdict on
    the step is `ended` (N,) bool, set by `reward` (called once per step), which the imagined core ORs in.
    """

    def __init__(self, spec: TaskSpec, base, reward_fn: StepFunction | None, termination_fn: StepFunction | None):
        self.spec, self.base = spec, base
        self.reward_fn, self.termination_fn = reward_fn, termination_fn
        self.terminates = base.terminates and termination_fn is None
        self.ended: np.ndarray | None = None
        """(N,) the termination function's verdict on the last step (None without a termination function)."""

    @property
    def command(self) -> np.ndarray:
        return self.base.command

    def reset(self, ids: np.ndarray, rngs: Sequence[np.random.Generator], commands: np.ndarray | None = None) -> None:
        self.base.reset(ids, rngs, commands)

    def reward(self, next_state, state, contact, foot_height, action, last_action):
        transition = Transition(
            self.spec, state, action, next_state, contact, foot_height, self.command.copy(), last_action
        )
        if self.termination_fn is not None:
            self.ended = call(self.termination_fn, transition, "termination", bool)
        if self.reward_fn is None:
            return self.base.reward(next_state, state, contact, foot_height, action, last_action)
        return call(self.reward_fn, transition, "reward", np.float64), {}

    def advance(self, steps: np.ndarray, rngs: Sequence[np.random.Generator]) -> None:
        self.base.advance(steps, rngs)
