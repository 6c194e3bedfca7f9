"""A scripted trotting policy: the reference behaviour the data collectors record for the world model.

A central pattern generator (one phase per env; diagonal pairs LF+RH and RF+LH in anti-phase) schedules stance and
swing. Swing feet are position-controlled: from where the foot lifts off to a touchdown point given by the Raibert
heuristic (half a stance stride ahead of the hip, plus a term on the measured velocity error), along an arc of
`swing_height`, through the leg's inverse kinematics. Stance legs are force-controlled through the same PD: the
ANYmal's PD (kp 80 N·m/rad, targets within 0.5 rad of the default pose) is far too soft to hold a 57 kg body on two
legs by position alone, so each stance leg gets the target q* = q + tau / kp that makes the PD output the torque
tau = -J^T f for its share f of a virtual-model wrench: body weight, height, roll/pitch and yaw-rate PD, and planar
velocity feedback, spread over the stance feet by weighted least squares. With a zero command the gait finishes its
swing and stands on four force-controlled legs.

The same softness bounds what the trot can track: commands are scaled down to a feasible envelope (`max_foot_speed`,
`max_lateral_speed`) rather than followed into a fall; the tracking error that leaves is measured by
`rwm-gym score --policy gait`. Leg geometry (joint offsets, axes, foot sites) is read from the task's MuJoCo model.

The policy reads only the 48-d observation (`rwm_gym.task.observation`), so it runs on the physics env and on the
imagined env alike.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from rwm_gym.physics.params import build_model
from rwm_gym.policies.base import gaussian_noise
from rwm_gym.policies.leg_kinematics import LegKinematics
from rwm_gym.spec import TaskSpec
from rwm_gym.task.observation import observation_slices

GRAVITY = 9.81  # m/s^2


@dataclass(frozen=True)
class GaitParams:
    """The numbers of the trot; units in the field docs."""

    frequency_hz: float = 2.5
    """Gait cycles per second (each leg steps once per cycle)."""
    duty: float = 0.6
    """Fraction of a cycle a foot is in stance (1)."""
    swing_height: float = 0.09
    """Peak foot lift over the stance height (m)."""
    stance_height: float = 0.56
    """Base origin above the foot centres (m)."""
    foot_x_offset: float = 0.05
    """Nominal foot position along x from the HFE joint, positive away from the body centre (m)."""
    foot_y_offset: float = 0.1
    """Nominal foot position along y from the HAA joint, positive outwards (m)."""
    lift_first: float = 0.15
    """Fraction of the swing spent rising before the foot travels (a loaded foot dragged forward pushes back) (1)."""
    swing_lead: float = 0.02
    """How far ahead of the clock the swing trajectory is sampled, to offset the PD's lag (s)."""
    raibert_gain: float = 0.3
    """Touchdown shift per unit of velocity error, measured minus desired (s)."""
    max_foot_shift: float = 0.15
    """Bound on the touchdown shift from the Raibert point, per axis (m)."""
    height_stiffness: float = 3000.0
    """Virtual vertical spring between the base and the stance feet (N/m)."""
    height_damping: float = 400.0
    """Virtual vertical damper (N·s/m)."""
    attitude_stiffness: float = 1000.0
    """Roll/pitch restoring torque per unit tilt (N·m/rad)."""
    attitude_damping: float = 40.0
    """Roll/pitch damping torque (N·m·s/rad)."""
    velocity_gain: float = 6.0
    """Planar force per unit mass and velocity error, commanded minus measured (1/s)."""
    yaw_gain: float = 40.0
    """Yaw torque per unit yaw-rate error (N·m·s/rad)."""
    friction: float = 0.6
    """Bound on the planar part of a stance foot's force as a fraction of its normal part (1)."""
    load_ramp: float = 0.15
    """Fraction of the stance over which a foot's share of the wrench ramps up after touchdown and down before
    lift-off (1)."""
    max_foot_speed: float = 1.0
    """Commands are scaled down so that no nominal foot point moves faster than this relative to the base (m/s);
    combined turning and walking beyond it tips the robot over."""
    max_lateral_speed: float = 0.4
    """Commands are scaled down so that the sideways speed stays under this (m/s)."""
    restart_speed: float = 0.3
    """Measured planar base speed above which a standing robot starts stepping to catch itself (m/s)."""


def _skew(r: np.ndarray) -> np.ndarray:
    """Cross-product matrices (..., 3, 3) of vectors (..., 3): skew(r) @ f = r x f."""
    x, y, z = r[..., 0], r[..., 1], r[..., 2]
    zero = np.zeros_like(x)
    return np.stack([np.stack([zero, -z, y], -1), np.stack([z, zero, -x], -1), np.stack([-y, x, zero], -1)], -2)


class GaitPolicy:
    """Vectorised scripted trot over N envs: `act(obs (N, O)) -> actions (N, A)` in [-1, 1].

    Keeps per-env state (gait phase, swing start points); `reset(ids, rngs)` starts new episodes with a random phase
    drawn from each env's generator, the same generators that draw the action noise, so a seed fixes the actions.
    `params` holds the gait's numbers; keyword overrides (e.g. `frequency_hz=2.5`) replace its fields.
    """

    name = "gait"

    def __init__(
        self,
        spec: TaskSpec,
        num_envs: int,
        *,
        action_noise: float = 0.0,
        params: GaitParams | None = None,
        **overrides: float,
    ):
        names = [f.name for f in dataclasses.fields(GaitParams)]
        unknown = sorted(set(overrides) - set(names))
        if unknown:
            raise ValueError(f"unknown gait parameter(s) {unknown}; known: {names}")
        self.params = p = dataclasses.replace(params or GaitParams(), **overrides)
        if not 0.5 <= p.duty < 1.0:
            raise ValueError(f"gait duty {p.duty} must be in [0.5, 1) for a trot")
        self.spec, self.num_envs, self.action_noise = spec, num_envs, action_noise
        model = build_model(spec)
        self.kin = LegKinematics.from_model(model, spec)
        if len(self.kin.hip) != 4:
            raise ValueError(f"task spec {spec.name}: the trot needs 4 legs, the robot has {len(self.kin.hip)}")
        self.mass = float(model.body_mass.sum())  # kg
        self.slices = observation_slices(spec)
        self.dt = spec.policy_dt
        self.default_pose = np.asarray(spec.actuator.default_pose, dtype=np.float64)
        # Diagonal pairs in anti-phase: LF and RH at phase 0, RF and LH half a cycle later (leg order LF, RF, LH, RH).
        self.leg_offset = np.array([0.0, 0.5, 0.5, 0.0])
        out = np.sign(self.kin.hip)
        self.nominal = np.stack(
            [
                self.kin.hip[:, 0] + self.kin.thigh[:, 0] + out[:, 0] * p.foot_x_offset,
                self.kin.hip[:, 1] + out[:, 1] * p.foot_y_offset,
                np.full(4, -p.stance_height),
            ],
            axis=-1,
        )  # (4, 3) m, base frame
        self.stance_time = p.duty / p.frequency_hz  # s

        n = num_envs
        self.rngs: list[np.random.Generator] = [np.random.default_rng(i) for i in range(n)]
        self.phase = np.zeros(n)
        """(N,) gait clock in [0, 1)."""
        self.liftoff = np.repeat(self.nominal[None], n, axis=0)
        """(N, 4, 3) where each foot left the ground, base frame (m)."""
        self.in_swing = np.zeros((n, 4), dtype=bool)

    def reset(self, ids: np.ndarray, rngs: list[np.random.Generator]) -> None:
        """Start new episodes in envs `ids` with one generator each (phase offset now, action noise later)."""
        ids = np.asarray(ids, dtype=int)
        if len(rngs) != len(ids):
            raise ValueError(f"GaitPolicy.reset: {len(ids)} env ids but {len(rngs)} generators")
        for i, rng in zip(ids, rngs):
            self.rngs[i] = rng
            self.phase[i] = rng.uniform()
        self.in_swing[ids] = False

    def _leg_phase(self, phase: np.ndarray) -> np.ndarray:
        return (phase[:, None] + self.leg_offset) % 1.0

    def act(self, obs: np.ndarray) -> np.ndarray:
        """Actions (N, A) in [-1, 1] for observations (N, O); advances the gait by one policy step."""
        p, s = self.params, self.slices
        obs = np.asarray(obs, dtype=np.float64)
        lin_vel, ang_vel = obs[:, s["base_lin_vel"]], obs[:, s["base_ang_vel"]]
        gravity, command = obs[:, s["projected_gravity"]], obs[:, s["command"]]
        q = (obs[:, s["joint_pos"]] + self.default_pose).reshape(-1, 4, 3)
        feet = self.kin.forward(q)  # (N, 4, 3) measured, base frame

        # Clock: advance, except to hold a standing robot in the four-foot support between two swings.
        moving = (np.linalg.norm(command, axis=1) > self.spec.command.standing_threshold) | (
            np.linalg.norm(lin_vel[:, :2], axis=1) > p.restart_speed
        )
        advanced = (self.phase + p.frequency_hz * self.dt) % 1.0
        hold = ~moving & ~self.in_swing.any(axis=1) & (self._leg_phase(advanced) >= p.duty).any(axis=1)
        self.phase = np.where(hold, self.phase, advanced)
        leg_phase = self._leg_phase(self.phase)
        swing = leg_phase >= p.duty
        desired = np.where(moving[:, None], command, 0.0)  # (vx, vy, yaw rate)
        # Scale the twist down where it would sweep a foot faster than the legs can follow, or step sideways faster
        # than the hip abduction (within 0.5 rad of its default) can carry the load.
        speed = np.linalg.norm(self._foot_velocity(desired), axis=-1).max(axis=1)
        scale = np.minimum(
            p.max_foot_speed / np.maximum(speed, 1e-9), p.max_lateral_speed / np.maximum(np.abs(desired[:, 1]), 1e-9)
        )
        desired = desired * np.minimum(1.0, scale)[:, None]

        targets = self._swing_targets(feet, swing, leg_phase, desired, lin_vel, ang_vel)
        q_swing = self.kin.inverse(targets)
        torque = self._stance_torques(q, feet, swing, leg_phase, hold, desired, lin_vel, ang_vel, gravity)
        target = np.where(
            swing[..., None], q_swing, q + torque / self.spec.actuator.per_joint("kp").reshape(q.shape[1:])
        )

        actions = (target.reshape(self.num_envs, -1) - self.default_pose) / self.spec.actuator.action_scale
        if self.action_noise > 0:
            actions = actions + gaussian_noise(self.rngs, self.action_noise, actions.shape[1])
        return np.clip(actions, -1.0, 1.0).astype(np.float32)

    def _foot_velocity(self, twist: np.ndarray) -> np.ndarray:
        """(N, 4, 2) planar velocity of a point at each nominal foot for base twists (N, 3) = (vx, vy, yaw rate)."""
        x, y = self.nominal[:, 0], self.nominal[:, 1]
        return np.stack([twist[:, :1] - twist[:, 2:] * y, twist[:, 1:2] + twist[:, 2:] * x], axis=-1)

    def _swing_targets(
        self,
        feet: np.ndarray,
        swing: np.ndarray,
        leg_phase: np.ndarray,
        desired: np.ndarray,
        lin_vel: np.ndarray,
        ang_vel: np.ndarray,
    ) -> np.ndarray:
        """Foot targets (N, 4, 3) of the swing legs: lift-off point -> Raibert touchdown point, on an arc."""
        p = self.params
        self.liftoff = np.where((swing & ~self.in_swing)[..., None], feet, self.liftoff)
        self.in_swing = swing
        measured = np.concatenate([lin_vel[:, :2], ang_vel[:, 2:]], axis=1)
        shift = np.clip(
            p.raibert_gain * (self._foot_velocity(measured) - self._foot_velocity(desired)),
            -p.max_foot_shift,
            p.max_foot_shift,
        )
        touchdown = self.nominal[:, :2] + 0.5 * self.stance_time * self._foot_velocity(desired) + shift
        progress = np.clip((leg_phase - p.duty + p.swing_lead * p.frequency_hz) / (1.0 - p.duty), 0.0, 1.0)
        travel = np.clip((progress - p.lift_first) / (1.0 - p.lift_first), 0.0, 1.0)
        blend = 0.5 - 0.5 * np.cos(np.pi * travel)
        xy = self.liftoff[..., :2] + (touchdown - self.liftoff[..., :2]) * blend[..., None]
        z = (
            self.liftoff[..., 2]
            + (-p.stance_height - self.liftoff[..., 2]) * blend
            + p.swing_height * np.sin(np.pi * progress)
        )
        return np.concatenate([xy, z[..., None]], axis=-1)

    def _stance_torques(
        self,
        q: np.ndarray,
        feet: np.ndarray,
        swing: np.ndarray,
        leg_phase: np.ndarray,
        hold: np.ndarray,
        desired: np.ndarray,
        lin_vel: np.ndarray,
        ang_vel: np.ndarray,
        gravity: np.ndarray,
    ) -> np.ndarray:
        """Joint torques (N, 4, 3) that make the stance feet push the virtual-model wrench onto the base."""
        p = self.params
        up = -gravity  # world up in the base frame
        stance = ~swing
        progress = np.clip(leg_phase / p.duty, 0.0, 1.0)
        weight = np.clip(np.minimum(progress, 1.0 - progress) / p.load_ramp, 0.05, 1.0) * stance
        weight = np.where(hold[:, None], 1.0, weight)  # standing: four equal feet
        # Base height above the stance feet (along world up) and its rate.
        height = np.sum(-np.einsum("nlk,nk->nl", feet, up) * weight, axis=1) / np.maximum(weight.sum(1), 1e-6)
        rise = np.einsum("nk,nk->n", lin_vel, up)
        lift = self.mass * GRAVITY + p.height_stiffness * (p.stance_height - height) - p.height_damping * rise
        planar = lin_vel[:, :2] - up[:, :2] * rise[:, None]
        force = lift[:, None] * up
        force[:, :2] += self.mass * p.velocity_gain * (desired[:, :2] - planar)
        tilt = np.cross(np.array([0.0, 0.0, 1.0]), up)  # ~ (-roll, -pitch, 0) for small angles
        moment = p.attitude_stiffness * tilt - p.attitude_damping * ang_vel * np.array([1.0, 1.0, 0.0])
        moment[:, 2] += p.yaw_gain * (desired[:, 2] - ang_vel[:, 2])
        wrench = np.concatenate([force, moment], axis=1)  # (N, 6)

        # Foot forces f (N, 12) with sum f_i = force, sum r_i x f_i = moment, least sum |f_i|^2 / w_i.
        blocks = np.concatenate([np.broadcast_to(np.eye(3), (*feet.shape[:2], 3, 3)), _skew(feet)], axis=-2)
        a = blocks.transpose(0, 2, 1, 3).reshape(-1, 6, 12)  # (N, 6, 12)
        w = np.repeat(weight, 3, axis=1)[:, None, :]
        gram = (a * w) @ a.transpose(0, 2, 1) + 1e-3 * np.eye(6)
        f = ((a * w).transpose(0, 2, 1) @ np.linalg.solve(gram, wrench[..., None]))[..., 0].reshape(-1, 4, 3)
        # Keep each foot pushing down and inside its friction pyramid (along the world up).
        normal = np.maximum(np.einsum("nlk,nk->nl", f, up), 0.0)
        tangent = f - np.einsum("nl,nk->nlk", np.einsum("nlk,nk->nl", f, up), up)
        size = np.linalg.norm(tangent, axis=-1, keepdims=True)
        tangent *= np.minimum(1.0, p.friction * normal[..., None] / np.maximum(size, 1e-9))
        f = normal[..., None] * up[:, None, :] + tangent
        return -np.einsum("nlij,nli->nlj", self.kin.jacobian(q), f) * stance[..., None]
