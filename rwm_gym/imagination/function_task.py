"""An imagined task whose reward and/or termination are functions of the predicted transition.

Built by `rwm_gym.imagination.tasks.make_task` when a spec names entry points (`[imagination] reward = "m:f"`) or the
imagined env gets `reward_fn=` / `termination_fn=` (see `rwm_gym.task.entry_points`). It keeps the commands of the
task underneath (velocity commands for a legged robot, none for a dm_control task) and replaces what was given.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from rwm_gym.spec import TaskSpec
from rwm_gym.task.entry_points import StepFunction, Transition, call


class CommandlessTask:
    """No commands, no reward of its own, never terminates: the base of a dm_control task with a reward function."""

    def __init__(self, num_envs: int):
        self.command = np.zeros((num_envs, 0), dtype=np.float32)

    def reset(self, ids: np.ndarray, rngs: Sequence[np.random.Generator]) -> None:
        pass

    def reward(self, next_state, state, contact, foot_height, action, last_action):
        raise NotImplementedError("CommandlessTask has no reward: give a reward function")

    def terminated(self, termination_logit: np.ndarray) -> np.ndarray:
        return np.zeros(len(termination_logit), dtype=bool)

    def advance(self, steps: np.ndarray, rngs: Sequence[np.random.Generator]) -> None:
        pass


class FunctionTask:
    """`base`'s commands; reward and termination from the given functions where given, else `base`'s.

    The core calls `reward` before `terminated` in each step; `terminated` reads the transition `reward` saw.
    """

    def __init__(self, spec: TaskSpec, base, reward_fn: StepFunction | None, termination_fn: StepFunction | None):
        self.spec, self.base = spec, base
        self.reward_fn, self.termination_fn = reward_fn, termination_fn
        self._transition: Transition | None = None

    @property
    def command(self) -> np.ndarray:
        return self.base.command

    def reset(self, ids: np.ndarray, rngs: Sequence[np.random.Generator]) -> None:
        self.base.reset(ids, rngs)

    def reward(self, next_state, state, contact, foot_height, action, last_action):
        self._transition = Transition(self.spec, state, action, next_state, contact, foot_height, self.command,
                                      last_action)
        if self.reward_fn is None:
            return self.base.reward(next_state, state, contact, foot_height, action, last_action)
        return call(self.reward_fn, self._transition, "reward", np.float64), {}

    def terminated(self, termination_logit: np.ndarray) -> np.ndarray:
        if self.termination_fn is None:
            return self.base.terminated(termination_logit)
        if self._transition is None:
            raise RuntimeError("FunctionTask.terminated called before reward in a step")
        done = call(self.termination_fn, self._transition, "termination", bool)
        self._transition = None
        return done

    def advance(self, steps: np.ndarray, rngs: Sequence[np.random.Generator]) -> None:
        self.base.advance(steps, rngs)
