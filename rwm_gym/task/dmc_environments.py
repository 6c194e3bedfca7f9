"""One dm_control environment behind one small interface: a suite task, or a task of `dm_control.manipulation`.

A spec's `[dm_control]` table names a suite task (`domain = "cheetah"`, `task = "run"`) or a manipulation task
(`domain = "manipulation"`, `task = "reach_site_features"`: the Kinova Jaco arm, built by dm_control's composer).
Both load dm_control's own models and task code; `DMCCore` (`rwm_gym.physics.dmc`) drives either through
`reseed`, `reset` and `step`, never through dm_control's own auto-reset and time limit (the spec's `episode_steps`
truncates episodes).

It lives beside the rewards because more than the physics env reads dm_control's task: the lift reward takes the
brick's corners from its model, the reach policy and the imagined arm's kinematics the arm's. It imports nothing else
of the package.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

MANIPULATION = "manipulation"
"""The `[dm_control] domain` of a `dm_control.manipulation` task."""


class DMCEnvironment(Protocol):
    """One dm_control environment: its `physics` (`.model.ptr` / `.data.ptr` are the raw MjModel / MjData)."""

    physics: object

    def control_timestep(self) -> float:
        """s, dm_control's control step."""

    def reseed(self, seed: int) -> None:
        """Seed the task's generator (the next reset draws its initial state from it)."""

    def reset(self) -> None:
        """A new episode: dm_control's own initial-state distribution."""

    def step(self, ctrl: np.ndarray, substeps: int) -> float:
        """Apply `ctrl` (the actuators' controls) for one control step; the task's reward after it."""


def _seed_words(seed: int) -> np.ndarray:
    return np.random.SeedSequence(int(seed)).generate_state(4)


class SuiteEnvironment:
    """A dm_control suite task, stepped as `control.Environment.step` does without its auto-reset."""

    def __init__(self, domain: str, task: str):
        from dm_control import suite

        self.env = suite.load(domain, task, task_kwargs={"random": None})
        self.physics = self.env.physics

    def control_timestep(self) -> float:
        return float(self.env.control_timestep())

    def reseed(self, seed: int) -> None:
        self.env.task.random.seed(_seed_words(seed))

    def reset(self) -> None:
        self.env.reset()

    def step(self, ctrl: np.ndarray, substeps: int) -> float:
        task, physics = self.env.task, self.physics
        task.before_step(ctrl, physics)
        physics.step(substeps)
        task.after_step(physics)
        return float(task.get_reward(physics))


class ManipulationEnvironment:
    """A `dm_control.manipulation` task (composer), without a time limit: its episodes never end by themselves."""

    def __init__(self, name: str):
        from dm_control import composer, manipulation
        from dm_control.manipulation.shared import registry

        if name not in manipulation.ALL:
            features = ", ".join(n for n in manipulation.ALL if n.endswith("_features"))
            raise ValueError(f"dm_control.manipulation has no task {name!r} (tasks on features: {features})")
        if not name.endswith("_features"):
            raise ValueError(f"dm_control.manipulation {name}: use a *_features task (the state is read from physics)")
        self.env = composer.Environment(registry.get_constructor(name)(), time_limit=float("inf"))

    @property
    def physics(self):
        """composer's physics (looked up each time: a reset may recompile it)."""
        return self.env.physics

    def control_timestep(self) -> float:
        return float(self.env.control_timestep())

    def reseed(self, seed: int) -> None:
        self.env.random_state.seed(_seed_words(seed))

    def reset(self) -> None:
        self.env.reset()

    def step(self, ctrl: np.ndarray, substeps: int) -> float:
        # composer runs its own substeps (control_timestep / physics timestep, checked equal to `substeps` at load)
        return float(self.env.step(ctrl).reward)


def load_environment(domain: str, task: str) -> DMCEnvironment:
    """The dm_control environment of a spec's `[dm_control]` domain and task, unseeded."""
    if domain == MANIPULATION:
        return ManipulationEnvironment(task)
    return SuiteEnvironment(domain, task)
