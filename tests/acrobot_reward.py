"""The acrobot-swingup reward as a user would write it for the imagined env: a function of the predicted state.

dm_control's own task code scores a physics whose joint angles are set from the state (the acrobot's target is fixed,
so the angles are all its reward reads). Named in a spec as `tests.acrobot_reward:swingup`.
"""

from __future__ import annotations

import mujoco
import numpy as np

_ENV = None


def swingup(transition) -> np.ndarray:
    global _ENV
    if _ENV is None:
        from dm_control import suite

        _ENV = suite.load("acrobot", "swingup", task_kwargs={"random": 0})
    physics = _ENV.physics
    angles = {
        j: np.arctan2(transition.column(f"joint_sin/{j}"), transition.column(f"joint_cos/{j}"))
        for j in ("shoulder", "elbow")
    }
    out = np.zeros(len(transition.next_state))
    for i in range(len(out)):
        for joint, angle in angles.items():
            physics.named.data.qpos[joint] = angle[i]
        mujoco.mj_kinematics(physics.model.ptr, physics.data.ptr)
        out[i] = _ENV.task.get_reward(physics)
    return out
