"""Physics that a predicted state obeys, applied to the predicted mean in the model's output path.

- `unit_gravity`: projected gravity is a unit vector. The predicted mean of the spec's `projected_gravity` group is
  taken to physical units, divided by its length and normalised again (differentiable).
- `joint_limits`: a joint stays inside the range of its MJCF joint. The predicted mean of the `joint_pos` group
  (joint position minus the default pose, as the physics env writes it) is clamped to [low, high] - default; the
  gradient passes as if unclamped (straight-through), so a prediction outside still learns where the truth is.

Neither touches the data, the targets or the metric: they only make the model's own outputs physical. They act on the
groups the spec declares (a task without them is unaffected). The limits are buffers of the model, so a checkpoint
carries the numbers it was trained with.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from rwm_gym.model.config import ModelConfig
from rwm_gym.spec import TaskSpec

GRAVITY, JOINTS = "projected_gravity", "joint_pos"


def joint_ranges(spec: TaskSpec) -> tuple[np.ndarray, np.ndarray]:
    """(J,) low and high joint positions in rad of the spec's actuated joints, from its MJCF (+-inf where a joint is
    not limited, or when the simulator ships its own model)."""
    joints = len(spec.actuator.joints)
    low, high = np.full(joints, -np.inf), np.full(joints, np.inf)
    if not spec.model:
        return low, high
    import mujoco

    model = mujoco.MjModel.from_xml_path(str(spec.model_path))
    for i, name in enumerate(spec.actuator.joints):
        joint = model.joint(name)
        if model.jnt_limited[joint.id]:
            low[i], high[i] = model.jnt_range[joint.id]
    return low, high


class StateConstraints(nn.Module):
    """forward(mean (..., S) normalised) -> the same with the switched-on constraints applied."""

    def __init__(self, config: ModelConfig, spec: TaskSpec) -> None:
        super().__init__()
        mean, std = (torch.as_tensor(a, dtype=torch.float32) for a in (spec.state_mean, spec.state_std))
        slices = spec.state_slices
        gravity = (
            torch.arange(slices[GRAVITY].start, slices[GRAVITY].stop)
            if config.unit_gravity and GRAVITY in slices
            else torch.zeros(0, dtype=torch.long)
        )
        self.register_buffer("gravity_index", gravity)
        self.register_buffer("gravity_mean", mean[gravity])
        self.register_buffer("gravity_std", std[gravity])
        joints = (
            torch.arange(slices[JOINTS].start, slices[JOINTS].stop)
            if config.joint_limits and JOINTS in slices
            else torch.zeros(0, dtype=torch.long)
        )
        low, high = joint_ranges(spec) if len(joints) else (np.zeros(0), np.zeros(0))
        default = np.asarray(spec.actuator.default_pose, dtype=np.float64)[: len(joints)]

        def to_state(limit: np.ndarray) -> torch.Tensor:  # a joint angle as the model's normalised state
            return (torch.as_tensor(limit - default, dtype=torch.float32) - mean[joints]) / std[joints]

        self.register_buffer("joint_index", joints)
        self.register_buffer("joint_low", to_state(low))
        self.register_buffer("joint_high", to_state(high))

    def forward(self, mean: torch.Tensor) -> torch.Tensor:
        if len(self.gravity_index):
            g = mean[..., self.gravity_index] * self.gravity_std + self.gravity_mean
            g = g / g.norm(dim=-1, keepdim=True).clamp(min=1e-6)
            mean = mean.index_copy(-1, self.gravity_index, (g - self.gravity_mean) / self.gravity_std)
        if len(self.joint_index):
            q = mean[..., self.joint_index]
            clamped = torch.maximum(torch.minimum(q, self.joint_high), self.joint_low)
            mean = mean.index_copy(-1, self.joint_index, q + (clamped - q).detach())
        return mean
