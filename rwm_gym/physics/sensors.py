"""Sensor bias: what a robot's sensors read differs from its state by a constant offset.

Two biases, both `PhysicsParams` fields: a joint encoder offset (rad, per joint), the zero of each encoder off the
joint's true zero, and a base-velocity estimate bias (m/s, base frame), a constant error of the state estimator's base
linear velocity. They change no dynamics: the robot moves as before, only its readings shift,

    joint_pos_read = joint_pos + offset,   base_lin_vel_read = base_lin_vel + bias   (base frame).

Where they act: on qpos and qvel, the arrays a dataset row holds and every state is measured from, as the sensor
noise of `make-measured` does (`rwm_gym.gap.measured.noisy_measurement`). The physics env reads its robot through
them (`LocomotionCore`: the observation, the state and the recorded qpos/qvel are the readings, as on a real robot),
and the re-simulation of measured data (`rwm_gym.gap.resim`) undoes them on each measured start state and applies
them to each simulated state. The bias on the base velocity is given in the base frame and added to the free joint's
world-frame linear velocity rotated by the base orientation of the same row, which the bias leaves alone, so reading
and undoing are exact inverses. The written MJCF (`gap.correct`) cannot hold them: they live in the env option
`physics`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rwm_gym.physics.params import PhysicsParams, per_joint
from rwm_gym.physics.robot import RobotLayout, quat_rotate


@dataclass(frozen=True)
class SensorBias:
    """The sensor bias of `params` on one robot layout."""

    qpos_adr: np.ndarray
    """(A,) qpos index of each actuated joint."""
    encoder_offset: np.ndarray
    """(A,) rad, added to each joint position read."""
    base_velocity_bias: np.ndarray
    """(3,) m/s in the base frame, added to the base linear velocity read."""

    @classmethod
    def of(cls, layout: RobotLayout, params: PhysicsParams | None) -> SensorBias | None:
        """The bias of `params` on `layout`'s joints; None where both are zero (the readings are the state)."""
        if params is None:
            return None
        offset = per_joint(params.encoder_offset, len(layout.qpos_adr), "encoder_offset")
        bias = np.asarray(params.base_velocity_bias, float)
        if bias.shape != (3,):
            raise ValueError(f"physics parameter 'base_velocity_bias' needs 3 values (m/s), got {bias.size}")
        if not offset.any() and not bias.any():
            return None
        return cls(np.asarray(layout.qpos_adr), offset, bias)

    def read(self, qpos: np.ndarray, qvel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Readings (new arrays) of true qpos (N, nq) and qvel (N, nv)."""
        return self._shift(qpos, qvel, 1.0)

    def unread(self, qpos: np.ndarray, qvel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """True qpos (N, nq) and qvel (N, nv) (new arrays) of readings: the inverse of `read`."""
        return self._shift(qpos, qvel, -1.0)

    def _shift(self, qpos: np.ndarray, qvel: np.ndarray, sign: float) -> tuple[np.ndarray, np.ndarray]:
        qpos, qvel = np.array(qpos, dtype=np.float64), np.array(qvel, dtype=np.float64)
        qpos[:, self.qpos_adr] += sign * self.encoder_offset
        if self.base_velocity_bias.any():
            bias = np.broadcast_to(self.base_velocity_bias, (len(qpos), 3))
            qvel[:, 0:3] += sign * quat_rotate(qpos[:, 3:7], bias)
        return qpos, qvel
