"""Kinematics of a quadruped's 3-joint legs (HAA about x, then HFE and KFE about y), read from its MuJoCo model.

Used by the scripted gait (`rwm_gym.policies.gait`) to turn foot positions into joint angles and foot forces into joint
torques. Everything is in the base frame at the base origin (x forward, y left, z up); arrays are (..., L, 3) over L
legs, angles in rad, lengths in m.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from rwm_gym.spec import TaskSpec

_FD_STEP = 1e-5  # rad, finite-difference step of the Jacobian


def _rot_x(angle: np.ndarray, v: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([v[..., 0], c * v[..., 1] - s * v[..., 2], s * v[..., 1] + c * v[..., 2]], axis=-1)


def _rot_y(angle: np.ndarray, v: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * v[..., 0] + s * v[..., 2], v[..., 1], -s * v[..., 0] + c * v[..., 2]], axis=-1)


@dataclass(frozen=True)
class LegKinematics:
    """Joint offsets of L legs at the zero pose, and each leg's default joint angles (to pick the IK branch)."""

    hip: np.ndarray
    """(L, 3) m, HAA joint in the base frame."""
    thigh: np.ndarray
    """(L, 3) m, HFE joint relative to the HAA joint."""
    shank: np.ndarray
    """(L, 3) m, KFE joint relative to the HFE joint."""
    foot: np.ndarray
    """(L, 3) m, foot centre relative to the KFE joint."""
    default_pose: np.ndarray
    """(L, 3) rad, the spec's default joint angles."""

    @classmethod
    def from_model(cls, model: mujoco.MjModel, spec: TaskSpec) -> LegKinematics:
        """Read the geometry of the spec's legs (joints leg-major in triples HAA, HFE, KFE; feet are sites).

        Requires each joint at its body's origin, axes x, y, y, and the foot site on the KFE joint's body.
        """
        joints = np.asarray([mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n) for n in spec.actuator.joints])
        feet = np.asarray([mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, n) for n in spec.privileged.feet])
        legs = len(feet)
        if (joints < 0).any() or (feet < 0).any() or len(joints) != 3 * legs:
            raise ValueError(f"robot model of task spec {spec.name}: need 3 named joints and one foot site per leg")
        joints = joints.reshape(legs, 3)
        bodies = model.jnt_bodyid[joints]
        axes = model.jnt_axis[joints]
        chain = (
            np.allclose(model.jnt_pos[joints], 0.0)
            and np.allclose(axes[:, 0], [1, 0, 0])
            and np.allclose(axes[:, 1:], [0, 1, 0])
            and np.array_equal(model.site_bodyid[feet], bodies[:, 2])
        )
        if not chain:
            raise ValueError(f"robot model of task spec {spec.name}: legs are not HAA(x)-HFE(y)-KFE(y) chains")
        return cls(
            hip=model.body_pos[bodies[:, 0]].copy(),
            thigh=model.body_pos[bodies[:, 1]].copy(),
            shank=model.body_pos[bodies[:, 2]].copy(),
            foot=model.site_pos[feet].copy(),
            default_pose=np.asarray(spec.actuator.default_pose, dtype=np.float64).reshape(legs, 3),
        )

    def forward(self, q: np.ndarray) -> np.ndarray:
        """Foot positions (..., L, 3) in the base frame from joint angles (..., L, 3)."""
        knee = self.shank + _rot_y(q[..., 2], np.broadcast_to(self.foot, q.shape))
        hfe = self.thigh + _rot_y(q[..., 1], knee)
        return self.hip + _rot_x(q[..., 0], hfe)

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """d foot / d q, (..., L, 3, 3) with [..., i, j] = d foot_i / d q_j (central differences)."""
        cols = []
        for j in range(3):
            dq = np.zeros(3)
            dq[j] = _FD_STEP
            cols.append((self.forward(q + dq) - self.forward(q - dq)) / (2 * _FD_STEP))
        return np.stack(cols, axis=-1)

    def inverse(self, feet: np.ndarray) -> np.ndarray:
        """Joint angles (..., L, 3) putting the feet at `feet` (..., L, 3), base frame.

        Of the two knee solutions, the one nearer the default pose is taken; unreachable targets are pulled onto the
        workspace boundary (leg fully stretched or folded) rather than failing.
        """
        p = feet - self.hip
        lateral = self.thigh[:, 1] + self.shank[:, 1] + self.foot[:, 1]  # (L,), unchanged by HFE/KFE rotations
        radius2 = p[..., 1] ** 2 + p[..., 2] ** 2
        below = -np.sqrt(np.maximum(radius2 - lateral**2, 1e-6)) - self.thigh[:, 2]  # sagittal z before HAA
        haa = np.arctan2(p[..., 2], p[..., 1]) - np.arctan2(below + self.thigh[:, 2], lateral)
        haa = (haa + np.pi) % (2 * np.pi) - np.pi
        # Sagittal plane as complex numbers x + i z; a y-rotation by q multiplies by exp(-i q).
        target = (p[..., 0] - self.thigh[:, 0]) + 1j * below
        upper = self.shank[:, 0] + 1j * self.shank[:, 2]
        lower = self.foot[:, 0] + 1j * self.foot[:, 2]
        cross = np.conj(upper) * lower  # |target|^2 = |upper|^2 + |lower|^2 + 2 Re(cross * exp(-i kfe))
        cos_arg = (np.abs(target) ** 2 - np.abs(upper) ** 2 - np.abs(lower) ** 2) / (2 * np.abs(cross))
        spread = np.arccos(np.clip(cos_arg, -1.0, 1.0))
        best = None
        for sign in (1.0, -1.0):
            kfe = np.angle(cross) - sign * spread
            hfe = np.angle(upper + np.exp(-1j * kfe) * lower) - np.angle(target)
            q = np.stack([haa, hfe, kfe], axis=-1)
            near = self.default_pose[:, 1:]  # wrap HFE and KFE into (-pi, pi] around the default pose
            q[..., 1:] = (q[..., 1:] - near + np.pi) % (2 * np.pi) - np.pi + near
            if best is None:
                best = q
            else:
                nearer = np.abs(q[..., 2] - self.default_pose[:, 2]) < np.abs(best[..., 2] - self.default_pose[:, 2])
                best = np.where(nearer[..., None], q, best)
        return best
