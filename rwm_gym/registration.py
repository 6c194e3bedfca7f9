"""Gymnasium registration, and how an env is named: a registered id, or the path of a task spec file.

Every spec in `envs/` registers its `physics_env_id` and `imagined_env_id` (read with `tomllib` only, so importing
the package imports neither MuJoCo nor torch). A spec of one's own needs no registration:

    gym.make("rwm_gym:Physics-v0", spec="my_robot.toml")          # physics (MuJoCo or dm_control)
    gym.make("rwm_gym:Imagined-v0", checkpoint="my_robot.safetensors")   # imagination (the checkpoint names its task)
    rwm-gym collect --env my_robot.toml ...                        # every command's --env takes a path too

The simulator behind a spec is chosen by the spec: a `[dm_control]` table runs the dm_control suite task, any other
spec runs its MJCF model as a velocity-tracking legged robot.
"""

from __future__ import annotations

import importlib
import tomllib
from pathlib import Path

import gymnasium as gym

from rwm_gym.resources import specs_dir
from rwm_gym.spec import TaskSpec, load_spec

SIMULATORS: dict[str, dict[str, str]] = {
    "mujoco": {
        "entry_point": "rwm_gym.physics.locomotion:LocomotionEnv",
        "vector_entry_point": "rwm_gym.vector.gym_vector_env:LocomotionGymVectorEnv",
        "core_entry_point": "rwm_gym.physics.locomotion:make_core",
    },
    "dm_control": {
        "entry_point": "rwm_gym.physics.dmc:DMCEnv",
        "vector_entry_point": "rwm_gym.vector.gym_vector_env:DMCGymVectorEnv",
        "core_entry_point": "rwm_gym.physics.dmc:make_core",
    },
}
"""Simulator name -> entry points of its single env, Gymnasium VectorEnv and the batched core the collectors drive."""

IMAGINED_ENTRY = {
    "entry_point": "rwm_gym.imagination.env:ImaginedEnv",
    "vector_entry_point": "rwm_gym.vector.gym_vector_env:ImaginedGymVectorEnv",
}


def simulator_of(tables: dict | TaskSpec) -> str:
    """ "dm_control" for a spec with a `[dm_control]` table, else "mujoco"."""
    extra = tables.extra if isinstance(tables, TaskSpec) else tables
    return "dm_control" if "dm_control" in extra else "mujoco"


def _shipped() -> dict[str, tuple[str, dict]]:
    """Spec name in envs/ -> (simulator, [task] table), for every shipped spec."""
    out = {}
    for path in sorted(specs_dir().glob("*.toml")):
        raw = tomllib.loads(path.read_text())
        out[path.stem] = (simulator_of(raw), raw["task"])
    return out


_SHIPPED = _shipped()

PHYSICS_ENVS: dict[str, dict] = {
    task["physics_env_id"]: {**SIMULATORS[sim], "kwargs": {"spec": name}} for name, (sim, task) in _SHIPPED.items()
}
"""Registered physics id -> entry points and kwargs (`spec`: the shipped spec's name)."""

DMC_SPECS: dict[str, str] = {
    task["physics_env_id"]: name for name, (sim, task) in _SHIPPED.items() if sim == "dm_control"
}
"""dm_control physics id -> shipped spec name (e.g. "DMC-Cheetah-Run-v0" -> "dmc_cheetah_run")."""

IMAGINED_ENVS: dict[str, dict] = {
    task["imagined_env_id"]: {**IMAGINED_ENTRY, "kwargs": {"env_id": task["imagined_env_id"]}}
    for name, (sim, task) in _SHIPPED.items()
}
"""Imagined id -> entry points. `checkpoint=None` loads the shipped checkpoint (ANYmal D only; the others need
checkpoint=PATH); a checkpoint of another task is refused."""

GENERIC_ENVS: dict[str, dict] = {
    "Physics-v0": {
        "entry_point": "rwm_gym.registration:make_physics_env",
        "vector_entry_point": "rwm_gym.registration:make_physics_vector_env",
        "kwargs": {},
    },
    "Imagined-v0": {**IMAGINED_ENTRY, "kwargs": {}},
}
"""Ids that take their task from an argument: `spec=` (a path, a shipped name or a TaskSpec) or `checkpoint=`."""


def resolve_spec(env: str | Path | TaskSpec) -> TaskSpec:
    """The task spec of a registered physics id, a shipped spec name, or a spec file path (`*.toml`).

    Raises ValueError with one line naming what was given and what is accepted.
    """
    if isinstance(env, TaskSpec):
        return env
    name = str(env)
    if name in PHYSICS_ENVS:
        return load_spec(PHYSICS_ENVS[name]["kwargs"]["spec"])
    if name in _SHIPPED:
        return load_spec(name)
    if name in IMAGINED_ENVS or name in GENERIC_ENVS:
        raise ValueError(f"{name!r} is not a physics env: give a physics id or a spec file")
    path = Path(name)
    if path.suffix == ".toml" or path.exists():
        if not path.is_file():
            raise ValueError(f"spec file {name!r} not found")
        try:
            return load_spec(path)
        except (OSError, UnicodeDecodeError) as err:
            raise ValueError(f"spec file {name!r} cannot be read ({err})") from None
    raise ValueError(
        f"unknown env {name!r}: not a registered physics id ({', '.join(sorted(PHYSICS_ENVS))}) "
        f"nor a spec file (*.toml)"
    )


def env_name(env: str | Path | TaskSpec) -> str:
    """What a dataset records as its env: the id or path as given, the physics id of a TaskSpec."""
    return env.physics_env_id if isinstance(env, TaskSpec) else str(env)


def _entry(spec: TaskSpec, kind: str):
    module, name = SIMULATORS[simulator_of(spec)][kind].split(":")
    return getattr(importlib.import_module(module), name)


def make_physics_core(env: str | Path | TaskSpec, num_envs: int, **kwargs):
    """The batched physics core (see `rwm_gym.vector`) of an env id, spec name, spec path or TaskSpec."""
    spec = resolve_spec(env)
    return _entry(spec, "core_entry_point")(spec=spec, num_envs=num_envs, **kwargs)


def make_physics_env(spec: str | Path | TaskSpec | None = None, **kwargs) -> gym.Env:
    """`gym.make("rwm_gym:Physics-v0", spec=...)`: the physics env of any spec; kwargs go to the env class."""
    if spec is None:
        raise ValueError("Physics-v0 needs spec=PATH (a task spec .toml) or a shipped spec name")
    task = resolve_spec(spec)
    return _entry(task, "entry_point")(spec=task, **kwargs)


def make_physics_vector_env(num_envs: int = 1, spec: str | Path | TaskSpec | None = None, **kwargs):
    """`gym.make_vec("rwm_gym:Physics-v0", num_envs=N, spec=..., vectorization_mode="vector_entry_point")`."""
    if spec is None:
        raise ValueError("Physics-v0 needs spec=PATH (a task spec .toml) or a shipped spec name")
    task = resolve_spec(spec)
    return _entry(task, "vector_entry_point")(num_envs=num_envs, spec=task, **kwargs)


def register_all() -> None:
    """Register every rwm-gym env id with Gymnasium (string entry points: no MuJoCo or torch imported)."""
    for env_id, entry in {**PHYSICS_ENVS, **IMAGINED_ENVS, **GENERIC_ENVS}.items():
        if env_id in gym.registry:
            continue
        gym.register(
            id=env_id,
            entry_point=entry["entry_point"],
            vector_entry_point=entry.get("vector_entry_point"),
            kwargs=entry["kwargs"],
            disable_env_checker=False,
        )
