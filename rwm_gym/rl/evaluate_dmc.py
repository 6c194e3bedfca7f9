"""Judge a policy on a dm_control task in physics: its return per episode and, for a manipulation task, its success.

Each seed is one env of the batched dm_control core (`rwm_gym.physics.dmc.DMCCore`), reset with that seed and run
for a full episode (the spec's `episode_steps`) with deterministic actions, so two policies' figures are comparable.
A manipulation task reports `info["success"]` each step (its goal met, `rwm_gym.task.manipulation_reward`); an
episode counts as a success when the goal is met at its last step, i.e. the policy got there and stayed.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from rwm_gym.spec import TaskSpec


@dataclass(frozen=True)
class EpisodeEvaluation:
    """A policy's full physics episodes on a dm_control task."""

    env_id: str
    returns: list[float]
    """Sum of the task's rewards per episode (a suite task's is at most 1000, a Jaco task's at most 250)."""
    episode_return: float
    """Mean of `returns`."""
    return_std: float
    success_rate: float | None
    """Share of episodes whose goal is met at their last step; None for a task that reports no success."""
    success_steps: float | None
    """Share of all steps at which the goal is met; None for a task that reports no success."""
    episodes: int
    steps: int
    """Policy steps per episode."""
    wall_s: float

    def to_dict(self) -> dict:
        return asdict(self)

    def summary(self) -> str:
        """One line: return, and success where the task has it."""
        line = (
            f"{self.env_id}: return {self.episode_return:.1f} +- {self.return_std:.1f} over {self.episodes} "
            f"episodes of {self.steps} steps"
        )
        if self.success_rate is not None:
            line += f", success {self.success_rate:.2f} at the end ({self.success_steps:.2f} of steps)"
        return line


def evaluate_episodes(policy, spec: str | TaskSpec, *, seeds: int = 5, steps: int | None = None) -> EpisodeEvaluation:
    """Run `policy` (an SB3 model, zip path or callable obs (N, O) -> actions (N, A)) for one episode per seed
    0..seeds-1 in the dm_control physics of `spec` (a physics id, spec name, path or TaskSpec)."""
    from rwm_gym.registration import make_physics_core, resolve_spec, simulator_of
    from rwm_gym.rl.evaluate_policy import as_policy

    task = resolve_spec(spec)
    if simulator_of(task) != "dm_control":
        raise ValueError(f"{task.name} is not a dm_control task (score it with rwm-gym score)")
    if seeds < 1 or (steps is not None and steps < 1):
        raise ValueError(f"seeds and steps must be >= 1, got {seeds} and {steps}")
    act, started = as_policy(policy), time.monotonic()
    core = make_physics_core(task, seeds)
    steps = steps or task.episode_steps
    obs = core.reset(np.arange(seeds), list(range(seeds)))
    returns, successes, success = np.zeros(seeds), np.zeros(seeds), None
    for _ in range(steps):
        obs, reward, _, _, info = core.step(np.clip(act(obs), -1.0, 1.0))
        returns += reward
        success = info.get("success")
        if success is not None:
            successes += success
    return EpisodeEvaluation(
        env_id=task.physics_env_id,
        returns=returns.tolist(),
        episode_return=float(returns.mean()),
        return_std=float(returns.std()),
        success_rate=None if success is None else float(np.mean(success)),
        success_steps=None if success is None else float(successes.sum() / (seeds * steps)),
        episodes=seeds,
        steps=steps,
        wall_s=time.monotonic() - started,
    )
