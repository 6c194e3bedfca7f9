"""Gymnasium registration of every environment the package ships."""

from __future__ import annotations

import gymnasium as gym

# id -> entry points of the single env, the Gymnasium VectorEnv, and the batched core the collectors drive.
PHYSICS_ENVS: dict[str, dict] = {
    "AnymalD-MuJoCo-v0": {
        "entry_point": "rwm_gym.physics.locomotion:LocomotionEnv",
        "kwargs": {"spec": "anymal_d"},
        "vector_entry_point": "rwm_gym.physics.batched:BatchedLocomotionVectorEnv",
        "core_entry_point": "rwm_gym.physics.batched:make_core",
    },
}


def register_all() -> None:
    for env_id, entry in PHYSICS_ENVS.items():
        if env_id in gym.registry:
            continue
        gym.register(
            id=env_id,
            entry_point=entry["entry_point"],
            vector_entry_point=entry.get("vector_entry_point"),
            kwargs=entry["kwargs"],
            disable_env_checker=False,
        )
