"""How a physics core is built: `PhysicsOptions`, one frozen dataclass read by `LocomotionCore` and taken by
`make_core` and every physics env (`LocomotionEnv`, the vector envs), whose keyword arguments are its fields. No
MuJoCo here, so code that only names the options imports light."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rwm_gym.physics.params import PhysicsParams, SolverSettings


@dataclass(frozen=True)
class PhysicsOptions:
    """The robot a physics core simulates and how it runs; every default is the task spec's robot, as its MJCF says."""

    xml_file: str | Path | None = None
    """Another MJCF of the robot (None: the task spec's model)."""
    physics: PhysicsParams | Mapping[str, object] | None = None
    """Physical parameters of the robot (a `PhysicsParams` or a dict of its fields, per-joint values allowed; None:
    the MJCF's)."""
    observation_noise: bool = False
    """Add the spec's uniform observation noise (`observation.noise`) to every observation."""
    nthread: int = 0
    """Threads of `mujoco.batch` stepping N > 1 simulations (0: all CPUs)."""
    resample_commands: bool = True
    """Resample commands on the spec's period (off: one command per episode)."""
    solver: SolverSettings | Mapping[str, int] | None = None
    """How exactly MuJoCo solves each step (a `SolverSettings` or a dict of its fields, e.g. {"iterations": 100};
    None: the MJCF's), not the robot."""
