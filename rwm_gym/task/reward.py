"""Reward and termination of the velocity-tracking task, shared by the physics and the imagined environments.

Everything here is a function of (state, privileged signals, command, action history) and of the feet-air-time timers
those signals drive, so a world model's predictions can be scored exactly like physics. Terms follow legged_gym / RWM;
each is multiplied by its weight from the spec and by the policy dt.

The terms and the timer rule are written once, against an array namespace `xp` (numpy by default): the torch
version (`rwm_gym.task.reward_torch`, differentiable, on any device) runs these same lines on tensors.
"""

from __future__ import annotations

from types import ModuleType

import numpy as np

from rwm_gym.spec import TaskSpec


def advance_air_time(air_time, last_contact, foot_contact, dt: float, target: float):
    """One step of the feet-air-time rule, as a pure function of numpy arrays or torch tensors alike.

    air_time (N, F) s, last_contact and foot_contact (N, F) bool. Returns the new (air_time, last_contact) and the
    touchdown term (N,): (air time - target) summed over the feet that touch down this step.
    """
    contact = foot_contact | last_contact  # filter single-step contact flicker
    first_contact = (air_time > 0.0) & contact
    air_time = air_time + dt
    term = ((air_time - target) * first_contact).sum(axis=1)
    return air_time * ~contact, foot_contact, term


class FeetAirTime:
    """Per-env, per-foot air-time timers (s), driven by foot contact flags.

    The reward pays (air time - target) once, at touchdown, when the command asks for motion.
    """

    def __init__(self, num_envs: int, num_feet: int):
        self.air_time = np.zeros((num_envs, num_feet))
        self.last_contact = np.zeros((num_envs, num_feet), dtype=bool)

    def reset(self, ids: np.ndarray) -> None:
        self.air_time[ids] = 0.0
        self.last_contact[ids] = False

    def update(self, foot_contact: np.ndarray, dt: float, target: float) -> np.ndarray:
        """Advance the timers by dt with contacts (N, F); return the touchdown term (N,)."""
        self.air_time, last, term = advance_air_time(self.air_time, self.last_contact, foot_contact, dt, target)
        self.last_contact = last.copy()
        return term


def reward_terms(
    spec: TaskSpec,
    state: np.ndarray,
    prev_state: np.ndarray,
    contact: np.ndarray,
    command: np.ndarray,
    action: np.ndarray,
    prev_action: np.ndarray,
    air_time_term: np.ndarray,
    xp: ModuleType = np,
) -> dict[str, np.ndarray]:
    """Unweighted reward terms, each (N,), for the transition prev_state --action--> state.

    state, prev_state (N, S) in SI units; contact (N, C) bool in spec order; command (N, 3) = (vx, vy, yaw rate);
    action, prev_action (N, A); air_time_term (N,) from `FeetAirTime.update`. xp: the arrays' namespace (numpy, or
    torch for tensors: see `rwm_gym.task.reward_torch`).
    """
    s = spec.state_slices
    lin_vel, ang_vel, gravity = (
        state[:, s["base_lin_vel"]],
        state[:, s["base_ang_vel"]],
        state[:, s["projected_gravity"]],
    )
    sigma = spec.reward.tracking_sigma
    moving = xp.linalg.norm(command[:, :2], axis=1) > spec.command.standing_threshold
    standing = xp.linalg.norm(command, axis=1) < spec.command.standing_threshold
    thighs = np.flatnonzero(np.isin(spec.privileged.contact_bodies, spec.privileged.thighs)).tolist()
    joint_acc = (state[:, s["joint_vel"]] - prev_state[:, s["joint_vel"]]) / spec.policy_dt
    terms = {
        "track_lin_vel_xy": xp.exp(-xp.sum((command[:, :2] - lin_vel[:, :2]) ** 2, axis=1) / sigma),
        "track_ang_vel_z": xp.exp(-((command[:, 2] - ang_vel[:, 2]) ** 2) / sigma),
        "lin_vel_z": lin_vel[:, 2] ** 2,
        "ang_vel_xy": xp.sum(ang_vel[:, :2] ** 2, axis=1),
        "torques": xp.sum(state[:, s["joint_torque"]] ** 2, axis=1),
        "dof_acc": xp.sum(joint_acc**2, axis=1),
        "action_rate": xp.sum((action - prev_action) ** 2, axis=1),
        "feet_air_time": air_time_term * moving,
        "thigh_contact": xp.sum(contact[:, thighs] * 1.0, axis=1),  # numpy: float64 counts
        "stand_still": xp.sum(xp.abs(state[:, s["joint_pos"]]), axis=1) * standing,
        "flat_orientation": xp.sum(gravity[:, :2] ** 2, axis=1),
    }
    return terms | biped_terms(spec, state, contact, moving, xp)


BIPED_TERMS = ("base_height", "feet_slip", "single_stance")
"""Terms computed only where the spec gives them a non-zero weight (a humanoid's; the quadrupeds' specs have none):

- `base_height`: (base height - `[reward] base_height_target`)², m²; needs a `base_height` state group;
- `feet_slip`: the base's squared horizontal speed (body frame) times the number of feet in contact, (m/s)²; a
  foot's own velocity is not a privileged signal, so the base's stands in for it, as in MuJoCo Playground's humanoid
  joystick tasks;
- `single_stance`: 1 while exactly one foot touches the ground and the command asks for motion (a walking biped's
  gait; a hop or a shuffle on both feet earns nothing).
"""


def biped_terms(spec: TaskSpec, state, contact, moving, xp: ModuleType = np) -> dict:
    """The `BIPED_TERMS` with a non-zero weight in the spec, each (N,); arguments as `reward_terms`'s, `moving` (N,)
    bool: the command asks for planar motion."""
    weights = spec.reward.weights
    wanted = [name for name in BIPED_TERMS if weights.get(name)]
    if not wanted:
        return {}
    s = spec.state_slices
    feet = np.flatnonzero(np.isin(spec.privileged.contact_bodies, spec.privileged.feet)).tolist()
    on_ground = xp.sum(contact[:, feet] * 1.0, axis=1)
    lin_vel = state[:, s["base_lin_vel"]]
    out = {}
    if "base_height" in wanted:
        out["base_height"] = (state[:, s["base_height"]][:, 0] - spec.reward.base_height_target) ** 2
    if "feet_slip" in wanted:
        out["feet_slip"] = xp.sum(lin_vel[:, :2] ** 2, axis=1) * on_ground
    if "single_stance" in wanted:
        out["single_stance"] = ((on_ground == 1) & moving) * xp.ones_like(lin_vel[:, 0])
    return out


def total_reward(spec: TaskSpec, terms: dict[str, np.ndarray]) -> np.ndarray:
    """Weighted sum of the terms times dt. (N,); numpy arrays or torch tensors alike. A biped term of weight 0 is
    left out (`biped_terms` does not compute it)."""
    weights = spec.reward.weights
    missing = {name for name, w in weights.items() if name not in terms and (w or name not in BIPED_TERMS)}
    if missing:
        raise ValueError(f"task spec {spec.name}: reward weights for unknown terms {sorted(missing)}")
    return sum(weights[name] * terms[name] for name in weights if name in terms) * spec.policy_dt
