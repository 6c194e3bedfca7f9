"""A collection's policy by name: `random`, `zero`, `gait`, `reach`, or the path of a trained SB3 policy.

Apart from `base` so that `gait` and `reach` (which import MuJoCo to read the robot) and `base` need not import each
other.
"""

from __future__ import annotations

from pathlib import Path

from rwm_gym.policies.base import Policy, RandomPolicy, SB3Policy, ZeroPolicy
from rwm_gym.spec import TaskSpec


def make_policy(name: str, spec: TaskSpec, num_envs: int, *, action_noise: float = 0.0) -> Policy:
    """`random`, `zero`, `gait` (a legged robot's trot), `reach` (an arm's reach, `rwm_gym.policies.reach`), or the
    path of an SB3 `.zip`."""
    if name == "zero":
        return ZeroPolicy(spec, num_envs, action_noise=action_noise)
    if name == "random":
        return RandomPolicy(spec, num_envs)
    if name == "gait":
        from rwm_gym.policies.gait import GaitPolicy

        return GaitPolicy(spec, num_envs, action_noise=action_noise)
    if name == "reach":
        from rwm_gym.policies.reach import ReachPolicy

        return ReachPolicy(spec, num_envs, action_noise=action_noise)
    if name.endswith(".zip"):
        if not Path(name).is_file():
            raise FileNotFoundError(f"policy file {name} not found")
        return SB3Policy(name, spec, num_envs, action_noise=action_noise)
    raise ValueError(f"unknown policy {name!r}: use 'random', 'zero', 'gait', 'reach' or the path of an SB3 .zip")
