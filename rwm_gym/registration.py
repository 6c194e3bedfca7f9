"""Gymnasium registration of every environment the package ships."""

from __future__ import annotations

import gymnasium as gym

from rwm_gym.spec import load_spec

# id -> entry points of the single env, the Gymnasium VectorEnv, and the batched core the collectors drive.
PHYSICS_ENVS: dict[str, dict] = {
    "AnymalD-MuJoCo-v0": {
        "entry_point": "rwm_gym.physics.locomotion:LocomotionEnv",
        "kwargs": {"spec": "anymal_d"},
        "vector_entry_point": "rwm_gym.physics.batched:BatchedLocomotionVectorEnv",
        "core_entry_point": "rwm_gym.physics.batched:make_core",
    },
}


# dm_control suite tasks: id -> spec name in envs/ (see rwm_gym.physics.dmc).
DMC_SPECS: dict[str, str] = {
    "DMC-Cheetah-Run-v0": "dmc_cheetah_run",
    "DMC-Walker-Walk-v0": "dmc_walker_walk",
    "DMC-Hopper-Hop-v0": "dmc_hopper_hop",
    "DMC-Quadruped-Walk-v0": "dmc_quadruped_walk",
    "DMC-Humanoid-Walk-v0": "dmc_humanoid_walk",
    "DMC-Finger-Spin-v0": "dmc_finger_spin",
}
for _env_id, _spec in DMC_SPECS.items():
    PHYSICS_ENVS[_env_id] = {
        "entry_point": "rwm_gym.physics.dmc:DMCEnv",
        "kwargs": {"spec": _spec},
        "vector_entry_point": "rwm_gym.physics.dmc:DMCVectorEnv",
        "core_entry_point": "rwm_gym.physics.dmc:make_core",
    }


# Imagined envs: id -> entry points. `checkpoint=None` loads the task's checkpoint shipped in assets/ (ANYmal D only:
# the dm_control ids need checkpoint=PATH); a checkpoint of another task is refused. Ids come from the specs'
# `imagined_env_id`.
IMAGINED_ENVS: dict[str, dict] = {}
for _env_id in ["RWM-AnymalD-v0"] + [load_spec(_spec).imagined_env_id for _spec in DMC_SPECS.values()]:
    IMAGINED_ENVS[_env_id] = {
        "entry_point": "rwm_gym.imagination.env:ImaginedEnv",
        "kwargs": {"env_id": _env_id},
        "vector_entry_point": "rwm_gym.imagination.vec_env:ImaginedVectorEnv",
    }


def register_all() -> None:
    for env_id, entry in {**PHYSICS_ENVS, **IMAGINED_ENVS}.items():
        if env_id in gym.registry:
            continue
        gym.register(
            id=env_id,
            entry_point=entry["entry_point"],
            vector_entry_point=entry.get("vector_entry_point"),
            kwargs=entry["kwargs"],
            disable_env_checker=False,
        )
