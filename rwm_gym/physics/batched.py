"""Many MuJoCo simulations of one task stepped together (`mujoco.batch` on a thread pool), as a Gymnasium
`VectorEnv` (`gym.make_vec(id, num_envs=N, vectorization_mode="vector_entry_point")`) and as an SB3 `VecEnv`.

For the same seeds they give the same transitions as N single `LocomotionEnv`s: all run `LocomotionCore`.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

from rwm_gym.physics.locomotion import LocomotionCore
from rwm_gym.physics.params import PhysicsParams, SolverSettings
from rwm_gym.spec import TaskSpec, load_spec
from rwm_gym.vector.gym_vector_env import CoreGymVectorEnv
from rwm_gym.vector.sb3_vec_env import CoreSB3VecEnv


def make_core(
    spec: str | TaskSpec = "anymal_d",
    num_envs: int = 1,
    *,
    xml_file: str | Path | None = None,
    physics: PhysicsParams | Mapping[str, object] | None = None,
    observation_noise: bool = False,
    nthread: int = 0,
    resample_commands: bool = True,
    solver: SolverSettings | Mapping[str, int] | None = None,
) -> LocomotionCore:
    task = spec if isinstance(spec, TaskSpec) else load_spec(spec)
    return LocomotionCore(task, num_envs, xml_file=xml_file, physics=physics, observation_noise=observation_noise,
                          nthread=nthread, resample_commands=resample_commands, solver=solver)


class LocomotionGymVectorEnv(CoreGymVectorEnv):
    """Gymnasium VectorEnv of N physics simulations; kwargs as `LocomotionEnv` plus `nthread` (0: all CPUs)."""

    def __init__(self, num_envs: int = 1, spec: str | TaskSpec = "anymal_d", **kwargs):
        kwargs.pop("render_mode", None)
        super().__init__(make_core(spec, num_envs, **kwargs))


class LocomotionSB3VecEnv(CoreSB3VecEnv):
    """SB3 VecEnv of N physics simulations; kwargs as `LocomotionEnv` plus `nthread` (0: all CPUs)."""

    def __init__(self, num_envs: int = 1, spec: str | TaskSpec = "anymal_d", **kwargs):
        super().__init__(make_core(spec, num_envs, **kwargs))


BatchedLocomotionVectorEnv, BatchedLocomotionVecEnv = LocomotionGymVectorEnv, LocomotionSB3VecEnv  # deprecated names
