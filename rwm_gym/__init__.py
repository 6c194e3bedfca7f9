"""rwm-gym: a learned robot world model (Robotic World Model, arXiv 2501.10100) as a Gymnasium environment.

Importing the package registers its environments with string entry points and nothing more: the names users import
from here (`from rwm_gym import ImaginedSB3VecEnv, PPOConfig`) are loaded on first use (PEP 562), so
`import rwm_gym` loads neither torch nor MuJoCo. `EXPORTS` is the one map from public name to defining module; the
modules may move, the names stay.
"""

from __future__ import annotations

import importlib
import os

# Offscreen rendering without a display: MuJoCo picks its GL backend when first imported, so choose EGL here unless
# the user already chose one. Only where libEGL exists: with MUJOCO_GL=egl and no libEGL, `import mujoco` itself fails
# (as on a GPU machine without libegl1), and physics needs no GL at all.
if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
    import ctypes.util

    if ctypes.util.find_library("EGL"):
        os.environ["MUJOCO_GL"] = "egl"

from rwm_gym.registration import register_all

__version__ = "0.3.0"

# public name -> the module that defines it (imported on first access)
EXPORTS: dict[str, str] = {
    # environments: the physics robot (MuJoCo) and its world-model twin, single and batched
    "LocomotionEnv": "rwm_gym.physics.locomotion",
    "LocomotionGymVectorEnv": "rwm_gym.vector.gym_vector_env",
    "LocomotionSB3VecEnv": "rwm_gym.vector.sb3_vec_env",
    "LocomotionRslRlVecEnv": "rwm_gym.vector.rsl_rl_vec_env",
    "ImaginedEnv": "rwm_gym.imagination.env",
    "ImaginedGymVectorEnv": "rwm_gym.vector.gym_vector_env",
    "ImaginedSB3VecEnv": "rwm_gym.vector.sb3_vec_env",
    "ImaginedRslRlVecEnv": "rwm_gym.vector.rsl_rl_vec_env",
    "DMCEnv": "rwm_gym.physics.dmc",
    "DMCGymVectorEnv": "rwm_gym.vector.gym_vector_env",
    "DMCSB3VecEnv": "rwm_gym.vector.sb3_vec_env",
    "ImaginationOptions": "rwm_gym.imagination.options",
    "PhysicsOptions": "rwm_gym.physics.options",
    "PhysicsParams": "rwm_gym.physics.params",
    "default_checkpoint": "rwm_gym.imagination.core",
    # policies: PPO in imagination or physics, MBPO, and the tracking score that judges them in physics
    "PPOConfig": "rwm_gym.rl.ppo",
    "make_ppo": "rwm_gym.rl.ppo",
    "learn": "rwm_gym.rl.ppo",
    "rsl_rl_train_cfg": "rwm_gym.rl.rsl_rl_train_cfg",
    "DistributedOnPolicyRunner": "rwm_gym.rl.rsl_rl_runner",
    "MBPOConfig": "rwm_gym.rl.mbpo",
    "mbpo": "rwm_gym.rl.mbpo",
    "SHACConfig": "rwm_gym.rl.shac",
    "DreamerConfig": "rwm_gym.rl.dreamer",
    "load_policy": "rwm_gym.policy_zip",
    "score": "rwm_gym.rl.score",
    "zero_policy": "rwm_gym.rl.score",
    "Evaluation": "rwm_gym.rl.evaluate_policy",
    # data: datasets (HDF5), collection, task specs
    "Dataset": "rwm_gym.data.dataset",
    "DatasetInfo": "rwm_gym.data.dataset",
    "DatasetWriter": "rwm_gym.data.dataset",
    "DatasetError": "rwm_gym.data.dataset",
    "write_dataset": "rwm_gym.data.dataset",
    "merge_datasets": "rwm_gym.data.dataset",
    "collect": "rwm_gym.data.collect",
    "TaskSpec": "rwm_gym.spec",
    "load_spec": "rwm_gym.spec",
    # world models: checkpoints (safetensors) and the step interface
    "load_checkpoint": "rwm_gym.model.checkpoint",
    "save_checkpoint": "rwm_gym.model.checkpoint",
    "read_meta": "rwm_gym.model.checkpoint",
    "physics_rows": "rwm_gym.model.lineage",
    "CheckpointError": "rwm_gym.model.checkpoint",
    "WorldModel": "rwm_gym.model.base",
    "ModelConfig": "rwm_gym.model.config",
    "TrainConfig": "rwm_gym.model.config",
    "assets_dir": "rwm_gym.resources",
}

__all__ = ["EXPORTS", "__version__", *EXPORTS]


def __getattr__(name: str):
    module = EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'rwm_gym' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # later lookups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *EXPORTS})


register_all()
