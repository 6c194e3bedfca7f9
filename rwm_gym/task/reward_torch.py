"""The velocity-tracking reward on torch tensors: differentiable, and on whatever device the tensors live.

For first-order policy optimisation through the world model (the reward's gradient flows back into predicted states
and the actions that produced them) and for imagined steps that stay on the GPU. The terms, weights and timer rule are
those of `rwm_gym.task.reward`, run on tensors (`xp=torch`), so the two versions cannot drift apart; the weights come
from the spec, as there.

Gradients: every term is a smooth function of (state, prev_state, action, prev_action) except the contact terms
(`thigh_contact`, `feet_air_time`, a biped's `single_stance`), which depend on contact flags only, and `stand_still`'s
|joint_pos| (subgradient sign(joint_pos)). Tensors are (N, ...) over envs; contacts are bool or 0/1 floats in the
spec's contact-body order.
"""

from __future__ import annotations

import numpy as np
import torch

from rwm_gym.spec import TaskSpec
from rwm_gym.task import reward
from rwm_gym.task.reward import advance_air_time, total_reward

__all__ = ["FeetAirTime", "reward_terms", "total_reward", "velocity_tracking_reward"]


class FeetAirTime:
    """Per-env, per-foot air-time timers (s) as tensors; the rule of `rwm_gym.task.reward.FeetAirTime`."""

    def __init__(
        self, num_envs: int, num_feet: int, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32
    ):
        self.air_time = torch.zeros((num_envs, num_feet), device=device, dtype=dtype)
        """(N, F) s since each foot left the ground (0 while it is down)."""
        self.last_contact = torch.zeros((num_envs, num_feet), device=device, dtype=torch.bool)
        """(N, F) the previous step's raw contact flags (the flicker filter's memory)."""

    def reset(self, ids: torch.Tensor | np.ndarray | list[int]) -> None:
        self.air_time[ids] = 0.0
        self.last_contact[ids] = False

    def update(self, foot_contact: torch.Tensor, dt: float, target: float) -> torch.Tensor:
        """Advance the timers by dt with contacts (N, F) (bool or 0/1); return the touchdown term (N,)."""
        self.air_time, last, term = advance_air_time(self.air_time, self.last_contact, foot_contact.bool(), dt, target)
        self.last_contact = last.clone()
        return term


def reward_terms(
    spec: TaskSpec,
    state: torch.Tensor,
    prev_state: torch.Tensor,
    contact: torch.Tensor,
    command: torch.Tensor,
    action: torch.Tensor,
    prev_action: torch.Tensor,
    air_time_term: torch.Tensor,
) -> dict[str, torch.Tensor]:
    """Unweighted reward terms, each (N,), for the transition prev_state --action--> state; the arguments of
    `rwm_gym.task.reward.reward_terms` as tensors (contact bool or 0/1, counted in the state's dtype)."""
    return reward.reward_terms(
        spec, state, prev_state, contact.to(state.dtype), command, action, prev_action, air_time_term, xp=torch
    )


def velocity_tracking_reward(
    spec: TaskSpec,
    air_time: FeetAirTime,
    next_state: torch.Tensor,
    state: torch.Tensor,
    contact: torch.Tensor,
    command: torch.Tensor,
    action: torch.Tensor,
    last_action: torch.Tensor,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Reward (N,) of the transition state --action--> next_state and its named terms, composed as
    `VelocityTrackingTask.reward` does: the feet's contacts in `next_state` drive `air_time` (advanced once per call),
    whose touchdown term is paid against the spec's air-time target; `command` (N, 3) is the one in force.

    next_state, state (N, S) SI units; contact (N, C) at next_state; action, last_action (N, A).
    """
    feet = np.flatnonzero(np.isin(spec.privileged.contact_bodies, spec.privileged.feet)).tolist()
    air = air_time.update(contact[:, feet], spec.policy_dt, spec.reward.feet_air_time_target)
    terms = reward_terms(spec, next_state, state, contact, command, action, last_action, air)
    return total_reward(spec, terms), terms
