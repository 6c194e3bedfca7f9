"""Drawing an imagined state with the robot's MuJoCo model, so the dream can be watched beside physics."""

from __future__ import annotations

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from rwm_gym.physics.params import build_model
from rwm_gym.physics.robot import RobotLayout
from rwm_gym.spec import TaskSpec


class DreamRenderer:
    """Poses the robot from predicted states: attitude from projected gravity plus integrated yaw rate, joints from
    predicted angles, horizontal position integrated from predicted body velocity, height from predicted foot
    heights."""

    def __init__(self, spec: TaskSpec, height: int = 480, width: int = 640, camera: str = "track"):
        self.spec = spec
        self.model = build_model(spec)
        self.data = mujoco.MjData(self.model)
        self.layout = RobotLayout.from_model(self.model, spec)
        self.renderer = mujoco.Renderer(self.model, height=height, width=width)
        self.camera = camera
        self.reset()

    def reset(self) -> None:
        self.position, self.yaw = np.zeros(2), 0.0

    def advance(self, state: np.ndarray, foot_height: np.ndarray, dt: float | None = None) -> None:
        """Integrate one predicted step (state in SI units) into the drawn pose."""
        dt = self.spec.policy_dt if dt is None else dt
        s = self.spec.state_slices
        gravity = state[s["projected_gravity"]] / max(np.linalg.norm(state[s["projected_gravity"]]), 1e-6)
        roll = np.arctan2(-gravity[1], -gravity[2])
        pitch = np.arcsin(np.clip(gravity[0], -1.0, 1.0))
        self.yaw += dt * float(state[s["base_ang_vel"]][2])
        rotation = Rotation.from_euler("ZYX", [self.yaw, pitch, roll])
        self.position += dt * rotation.apply(state[s["base_lin_vel"]])[:2]
        qpos = self.data.qpos
        qpos[:2], qpos[2] = self.position, 0.0
        qpos[3:7] = np.roll(rotation.as_quat(), 1)  # (x, y, z, w) -> MuJoCo's (w, x, y, z)
        qpos[self.layout.qpos_adr] = self.layout.default_pose + state[s["joint_pos"]]
        mujoco.mj_kinematics(self.model, self.data)
        feet_z = self.data.site_xpos[self.layout.foot_site_ids, 2] - self.layout.foot_radius
        qpos[2] = float(np.min(foot_height - feet_z)) if len(feet_z) else 0.5
        mujoco.mj_forward(self.model, self.data)

    def render(self) -> np.ndarray:
        self.renderer.update_scene(self.data, camera=self.camera)
        return self.renderer.render()

    def close(self) -> None:
        self.renderer.close()
