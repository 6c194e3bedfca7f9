"""Drive torque-speed limit: the torque a drive can give falls linearly with joint speed above a knee.

An electric drive's torque is capped by its current limit at low speed; above a knee speed the back-EMF eats the
supply voltage and the available torque falls, about linearly, to zero at the no-load speed:

    limit(qdot) = max(0, tau_max - slope * max(0, |qdot| - knee)),

with tau_max the drive's torque limit (the actuator's force range, so `torque_limit` still applies), `slope` in
N·m·s/rad and `knee` in rad/s, per joint.

Where it acts: MuJoCo's force range is a constant, so, like the dead band of `backlash`, the simulators step the physics
one step at a time while the limit is set and rewrite each actuator's control before every physics step so that
MuJoCo's position-actuator force gain * ctrl + bias(q, qdot) equals the PD force clipped to limit(qdot) at that step's
joint position and speed. It acts at the physics rate and is memoryless, so re-simulation from measured states
reproduces it exactly. Limits: with `action_delay` also set MuJoCo delays the rewritten control, so the clip is that of
the state a delay earlier; the written MJCF (`gap.correct`) cannot hold it: it lives in the env option `physics`.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np


@dataclass(frozen=True)
class TorqueSpeedLimit:
    """The torque-speed limit of the actuated joints of one compiled model."""

    actuator_ids: np.ndarray
    """(A,) position actuators of the actuated joints."""
    qpos_adr: np.ndarray
    """(A,) qpos index of each one's joint."""
    dof_adr: np.ndarray
    """(A,) qvel index of each one's joint."""
    gain: np.ndarray
    """(A,) actuator gainprm[0] (N·m per rad of target)."""
    bias: np.ndarray
    """(A, 3) actuator biasprm[:3]: force = gain * ctrl + bias . (1, q, qdot)."""
    torque_max: np.ndarray
    """(A,) N·m, the force range's upper end: the limit below the knee."""
    slope: np.ndarray
    """(A,) N·m·s/rad."""
    knee: np.ndarray
    """(A,) rad/s."""

    @classmethod
    def from_model(
        cls, model: mujoco.MjModel, joints: list[str] | tuple[str, ...], slope: np.ndarray, knee: np.ndarray
    ) -> TorqueSpeedLimit | None:
        """The limit with `slope` (A,) N·m·s/rad above `knee` (A,) rad/s at the position actuators named as
        `joints`; None where every slope is 0."""
        slope, knee = np.asarray(slope, float), np.asarray(knee, float)
        if np.any(slope < 0) or np.any(knee < 0):
            raise ValueError(
                f"physics parameters 'torque_speed_slope' and 'torque_speed_knee' must be >= 0, got "
                f"{slope.tolist()} and {knee.tolist()}"
            )
        if not np.any(slope > 0):
            return None
        actuators = np.array([mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, n) for n in joints])
        joint_ids = model.actuator_trnid[actuators, 0]
        return cls(
            actuators,
            model.jnt_qposadr[joint_ids].copy(),
            model.jnt_dofadr[joint_ids].copy(),
            model.actuator_gainprm[actuators, 0].copy(),
            model.actuator_biasprm[actuators, :3].copy(),
            model.actuator_forcerange[actuators, 1].copy(),
            slope,
            knee,
        )

    def limit(self, qdot: np.ndarray) -> np.ndarray:
        """(N, A) N·m available at joint speeds `qdot` (N, A) rad/s."""
        return np.maximum(0.0, self.torque_max - self.slope * np.maximum(0.0, np.abs(qdot) - self.knee))

    def control(self, ctrl: np.ndarray, qpos: np.ndarray, qvel: np.ndarray) -> np.ndarray:
        """Rewritten controls (N, nu) for controls `ctrl` (N, nu) at qpos (N, nq) and qvel (N, nv)."""
        out = np.array(ctrl, dtype=np.float64)
        q, qdot = qpos[:, self.qpos_adr], qvel[:, self.dof_adr]
        bias = self.bias[:, 0] + self.bias[:, 1] * q + self.bias[:, 2] * qdot
        force = self.gain * out[:, self.actuator_ids] + bias
        cap = self.limit(qdot)
        out[:, self.actuator_ids] = (np.clip(force, -cap, cap) - bias) / self.gain
        return out
