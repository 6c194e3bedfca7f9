"""Reward and termination of the velocity-tracking task, shared by the physics and the imagined environments.

Everything here is a function of (state, privileged signals, command, action history) and of the feet-air-time timers
those signals drive, so a world model's predictions can be scored exactly like physics. Terms follow legged_gym / RWM;
each is multiplied by its weight from the spec and by the policy dt.
"""

from __future__ import annotations

import numpy as np

from rwm_gym.spec import TaskSpec


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
        contact = foot_contact | self.last_contact  # filter single-step contact flicker
        self.last_contact = foot_contact.copy()
        first_contact = (self.air_time > 0.0) & contact
        self.air_time += dt
        term = np.sum((self.air_time - target) * first_contact, axis=1)
        self.air_time *= ~contact
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
) -> dict[str, np.ndarray]:
    """Unweighted reward terms, each (N,), for the transition prev_state --action--> state.

    state, prev_state (N, S) in SI units; contact (N, C) bool in spec order; command (N, 3) = (vx, vy, yaw rate);
    action, prev_action (N, A); air_time_term (N,) from `FeetAirTime.update`.
    """
    s = spec.state_slices
    lin_vel, ang_vel, gravity = state[:, s["base_lin_vel"]], state[:, s["base_ang_vel"]], state[:, s["projected_gravity"]]
    sigma = spec.reward.tracking_sigma
    moving = np.linalg.norm(command[:, :2], axis=1) > spec.command.standing_threshold
    standing = np.linalg.norm(command, axis=1) < spec.command.standing_threshold
    thighs = np.isin(spec.privileged.contact_bodies, spec.privileged.thighs)
    joint_acc = (state[:, s["joint_vel"]] - prev_state[:, s["joint_vel"]]) / spec.policy_dt
    return {
        "track_lin_vel_xy": np.exp(-np.sum((command[:, :2] - lin_vel[:, :2]) ** 2, axis=1) / sigma),
        "track_ang_vel_z": np.exp(-((command[:, 2] - ang_vel[:, 2]) ** 2) / sigma),
        "lin_vel_z": lin_vel[:, 2] ** 2,
        "ang_vel_xy": np.sum(ang_vel[:, :2] ** 2, axis=1),
        "torques": np.sum(state[:, s["joint_torque"]] ** 2, axis=1),
        "dof_acc": np.sum(joint_acc**2, axis=1),
        "action_rate": np.sum((action - prev_action) ** 2, axis=1),
        "feet_air_time": air_time_term * moving,
        "thigh_contact": np.sum(contact[:, thighs], axis=1).astype(np.float64),
        "stand_still": np.sum(np.abs(state[:, s["joint_pos"]]), axis=1) * standing,
        "flat_orientation": np.sum(gravity[:, :2] ** 2, axis=1),
    }


def total_reward(spec: TaskSpec, terms: dict[str, np.ndarray]) -> np.ndarray:
    """Weighted sum of the terms times dt. (N,)."""
    weights = spec.reward.weights
    missing = set(weights) - set(terms)
    if missing:
        raise ValueError(f"task spec {spec.name}: reward weights for unknown terms {sorted(missing)}")
    return sum(weights[name] * terms[name] for name in weights) * spec.policy_dt
