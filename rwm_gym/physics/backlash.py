"""Gear backlash: a dead band of total width b (rad) between each drive's motor and its link.

Model (the "dead-zone" model of backlash, with the motor's inertia neglected against its stiff position loop): the
motor turns freely inside the gap, so the drive passes torque only once the position error has closed the gap,

    tau = strength * (kp * D(target - q) - kd * qdot),   D(e) = e - clip(e, -b/2, b/2),

saturated at the torque limit as before. With the load on one side (e.g. a leg in stance) the link settles b/2 short
of its target; when the load reverses the link travels through the gap with no restoring torque but damping.

Where it acts: MuJoCo's position actuators cannot hold a dead band, so the simulators (`SingleSimulator`,
`BatchSimulator`) step the physics one step at a time while backlash is set and rewrite each actuator's control before
every physics step to q + D(target - q), which makes MuJoCo's force kp * (ctrl - q) equal kp * D(target - q) exactly
at that step's joint position. The dead band therefore acts at the physics rate (`spec.physics_dt`), not the policy
rate. It is memoryless (no hidden state beyond qpos), so re-simulation from measured states reproduces it exactly.

Limits: no motor-side inertia, no impact when the gap closes, damping acts on the link velocity throughout; with
`action_delay` also set MuJoCo delays the rewritten control, so inside the band the force lags the joint position by the
delay (outside the band the two agree). The written MJCF (`gap.correct`) cannot hold the dead band: it lives in the env
option `physics.backlash`.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np


@dataclass(frozen=True)
class DeadBand:
    """Backlash of the actuated joints of one compiled model."""

    actuator_ids: np.ndarray
    """(A,) actuators with a dead band."""
    qpos_adr: np.ndarray
    """(A,) qpos index of each one's joint."""
    half_width: np.ndarray
    """(A,) rad, b/2 per actuator."""

    @classmethod
    def from_model(
        cls, model: mujoco.MjModel, joints: list[str] | tuple[str, ...], width: np.ndarray
    ) -> DeadBand | None:
        """The dead band of total `width` (A,) rad at the position actuators named as `joints`; None if all are 0."""
        width = np.asarray(width, float)
        if np.any(width < 0):
            raise ValueError(f"physics parameter 'backlash' must be >= 0 rad, got {width.tolist()}")
        if not np.any(width > 0):
            return None
        actuators = np.array([mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, n) for n in joints])
        joint_ids = model.actuator_trnid[actuators, 0]
        return cls(actuators, model.jnt_qposadr[joint_ids].copy(), 0.5 * width)

    def control(self, ctrl: np.ndarray, qpos: np.ndarray, qvel: np.ndarray | None = None) -> np.ndarray:
        """Rewritten controls (N, nu) for position targets `ctrl` (N, nu) at joint positions `qpos` (N, nq) (the
        dead band does not depend on the velocities `qvel`)."""
        out = np.array(ctrl, dtype=np.float64)
        q = qpos[:, self.qpos_adr]
        error = out[:, self.actuator_ids] - q
        out[:, self.actuator_ids] = q + error - np.clip(error, -self.half_width, self.half_width)
        return out
