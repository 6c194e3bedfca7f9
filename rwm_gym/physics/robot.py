"""Reading the task's state and privileged signals out of MuJoCo arrays, for one or many simulations at once.

`RobotLayout` resolves, once per model, where each quantity lives (joint addresses, contact sensors, foot sites);
`measure` turns raw simulation arrays of shape (N, ...) into the world-model state (N, S) and the privileged signals.
The physics env, the batched env and the imagined env's renderer all go through here.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from rwm_gym.spec import TaskSpec


@dataclass(frozen=True)
class RobotLayout:
    """Where the spec's joints, actuators and sensors sit in the MuJoCo model's arrays."""

    qpos_adr: np.ndarray
    """(A,) qpos index of each actuated joint, spec order."""
    dof_adr: np.ndarray
    """(A,) qvel index of each actuated joint."""
    actuator_ids: np.ndarray
    """(A,) actuator index driving each joint."""
    contact_sensor_adr: np.ndarray
    """(C,) sensordata index of each contact body's normal-force sensor."""
    termination_sensor_adr: np.ndarray
    """(T,) sensordata index of each termination body's sensor."""
    foot_site_ids: np.ndarray
    """(F,) site at each foot centre."""
    foot_radius: np.ndarray
    """(F,) m, radius of each foot's sphere or capsule (0 for a box, whose site sits on its bottom face), so foot
    height is the lowest point above z = 0."""
    default_pose: np.ndarray
    """(A,) rad."""

    @classmethod
    def from_model(cls, model: mujoco.MjModel, spec: TaskSpec) -> RobotLayout:
        def obj_id(kind: mujoco.mjtObj, name: str, what: str) -> int:
            i = mujoco.mj_name2id(model, kind, name)
            if i < 0:
                raise ValueError(f"robot model has no {what} named {name!r}, required by task spec {spec.name}")
            return i

        joints = [obj_id(mujoco.mjtObj.mjOBJ_JOINT, n, "joint") for n in spec.actuator.joints]
        actuators = [obj_id(mujoco.mjtObj.mjOBJ_ACTUATOR, n, "actuator") for n in spec.actuator.joints]

        def sensor_adr(body: str) -> int:
            return int(model.sensor_adr[obj_id(mujoco.mjtObj.mjOBJ_SENSOR, f"contact_{body}", "contact sensor")])

        feet = [obj_id(mujoco.mjtObj.mjOBJ_SITE, n, "foot site") for n in spec.privileged.feet]
        foot_geoms = [obj_id(mujoco.mjtObj.mjOBJ_GEOM, n, "foot geom") for n in spec.privileged.feet]
        return cls(
            qpos_adr=model.jnt_qposadr[joints].copy(),
            dof_adr=model.jnt_dofadr[joints].copy(),
            actuator_ids=np.asarray(actuators),
            contact_sensor_adr=np.asarray([sensor_adr(b) for b in spec.privileged.contact_bodies], dtype=int),
            termination_sensor_adr=np.asarray([sensor_adr(b) for b in spec.privileged.termination_bodies], dtype=int),
            foot_site_ids=np.asarray(feet, dtype=int),
            foot_radius=np.where(
                model.geom_type[foot_geoms] == int(mujoco.mjtGeom.mjGEOM_BOX), 0.0, model.geom_size[foot_geoms, 0]
            ),
            default_pose=np.asarray(spec.actuator.default_pose),
        )


@dataclass
class Measurement:
    """What one policy step observes of N robots."""

    state: np.ndarray
    """(N, S) world-model state in the spec's column order (SI units, unnormalised)."""
    contact: np.ndarray
    """(N, C) bool, net contact force above the spec's threshold on each contact body."""
    foot_height: np.ndarray
    """(N, F) m, lowest point of each foot above the ground plane."""
    terminated: np.ndarray
    """(N,) bool, a termination body touches something."""


def quat_rotate(quat: np.ndarray, vec: np.ndarray) -> np.ndarray:
    """Rotate body-frame vectors into the world frame by unit quaternions (w, x, y, z). Shapes (N, 4), (N, 3) ->
    (N, 3); the inverse of `quat_rotate_inverse`."""
    w, xyz = quat[:, :1], quat[:, 1:]
    t = 2.0 * np.cross(xyz, vec)
    return vec + w * t + np.cross(xyz, t)


def quat_rotate_inverse(quat: np.ndarray, vec: np.ndarray) -> np.ndarray:
    """Rotate world vectors into the body frames of unit quaternions (w, x, y, z). Shapes (N, 4), (N, 3) -> (N, 3)."""
    w, xyz = quat[:, :1], quat[:, 1:]
    t = 2.0 * np.cross(xyz, vec)
    return vec - w * t + np.cross(xyz, t)


def measure(
    layout: RobotLayout,
    spec: TaskSpec,
    qpos: np.ndarray,
    qvel: np.ndarray,
    actuator_force: np.ndarray,
    sensordata: np.ndarray,
    site_xpos: np.ndarray,
) -> Measurement:
    """Build the state and privileged signals from raw arrays, all with a leading batch axis N.

    qpos (N, nq) with a free base first; qvel (N, nv); actuator_force (N, nu); sensordata (N, nsensordata);
    site_xpos (N, nsite, 3). Base linear velocity is in the body frame; base angular velocity is the free joint's,
    already in the body frame.
    """
    quat = qpos[:, 3:7]
    lin_vel = quat_rotate_inverse(quat, qvel[:, 0:3])
    ang_vel = qvel[:, 3:6]
    gravity = quat_rotate_inverse(quat, np.broadcast_to([0.0, 0.0, -1.0], lin_vel.shape))
    parts = {
        "base_height": qpos[:, 2:3],  # m above the floor (z = 0); an optional group (a biped's base_height reward)
        "base_lin_vel": lin_vel,
        "base_ang_vel": ang_vel,
        "projected_gravity": gravity,
        "joint_pos": qpos[:, layout.qpos_adr] - layout.default_pose,
        "joint_vel": qvel[:, layout.dof_adr],
        "joint_torque": actuator_force[:, layout.actuator_ids],
    }
    state = np.concatenate([parts[g.name] for g in spec.state], axis=1)
    threshold = spec.privileged.contact_threshold
    contact = sensordata[:, layout.contact_sensor_adr] > threshold
    terminated = np.any(sensordata[:, layout.termination_sensor_adr] > threshold, axis=1)
    foot_height = site_xpos[:, layout.foot_site_ids, 2] - layout.foot_radius
    return Measurement(state.astype(np.float32), contact, foot_height.astype(np.float32), terminated)
