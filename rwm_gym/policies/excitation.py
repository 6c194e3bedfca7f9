"""The excitation policy of `make-measured`: an open-loop trot plus correlated random actions plus rare target jumps.

System identification needs data that excites every candidate effect: stance and swing (payload, ground friction),
both signs of joint velocity at many speeds (friction, damping), fast target changes (delay, armature, PD gains) and
torques at the drives' limits (torque limit, motor strength). A walking gait alone is too regular; random actions alone
rarely load the legs. Deterministic given the per-episode generators (see `rwm_gym.policies.base.Policy`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rwm_gym.spec import TaskSpec


@dataclass(frozen=True)
class ExcitationConfig:
    """Amplitudes in action units (the spec's `action_scale` turns them into rad)."""

    gait_amplitude: float = 0.5
    """Swing amplitude of the trot on the knee (HFE gets half)."""
    frequency_hz: tuple[float, float] = (1.2, 2.5)
    """Range of the trot frequency, drawn per episode."""
    noise_scale: float = 0.15
    """Std of the correlated random action added on top."""
    correlation: float = 0.6
    """Step-to-step correlation of the random action."""
    jump_probability: float = 0.01
    """Per step and joint, chance of a target jump (drives the torque to its limit)."""
    jump_scale: float = 1.0
    """Size of a target jump, in action units."""


class ExcitationPolicy:
    """Trot + noise + jumps for N envs; actions (N, A) in [-1, 1], joints in the spec's leg-major order."""

    name = "excitation"

    def __init__(self, spec: TaskSpec, num_envs: int, config: ExcitationConfig | None = None):
        self.config = config or ExcitationConfig()
        self.dt = spec.policy_dt
        """s, the task's policy step: the trot's phase advances by 2 pi f dt per action."""
        a = spec.action_dim
        legs = a // 3
        # Diagonal trot: LF+RH in phase, RF+LH opposite. Hind legs' HFE/KFE signs flip (default pose mirrors them).
        self.leg_phase = np.repeat(np.array([0.0, np.pi, np.pi, 0.0])[:legs], 3)
        mirror = np.sign(np.asarray(spec.actuator.default_pose).reshape(legs, 3)[:, 2])
        self.knee_sign = np.repeat(-mirror, 3)  # flex the knee further
        self.joint_kind = np.tile([0, 1, 2], legs)
        self.phase = np.zeros(num_envs)
        self.freq = np.ones(num_envs)
        self.noise = np.zeros((num_envs, a))
        self.rngs: list[np.random.Generator] = [np.random.default_rng(0) for _ in range(num_envs)]

    def reset(self, ids: np.ndarray, rngs: list[np.random.Generator]) -> None:
        c = self.config
        for i, rng in zip(ids, rngs):
            self.rngs[i] = rng
            self.phase[i] = rng.uniform(0, 2 * np.pi)
            self.freq[i] = rng.uniform(*c.frequency_hz)
            self.noise[i] = rng.normal(0.0, c.noise_scale, self.noise.shape[1])

    def act(self, obs: np.ndarray) -> np.ndarray:
        c = self.config
        self.phase += 2 * np.pi * self.freq * self.dt
        phi = self.phase[:, None] + self.leg_phase[None]
        swing = np.maximum(np.sin(phi), 0.0)
        gait = np.where(
            self.joint_kind == 2,
            self.knee_sign * c.gait_amplitude * swing,
            np.where(self.joint_kind == 1, 0.5 * c.gait_amplitude * np.cos(phi), 0.0),
        )
        for i, rng in enumerate(self.rngs):
            fresh = rng.normal(0.0, c.noise_scale, self.noise.shape[1])
            jumps = rng.random(self.noise.shape[1]) < c.jump_probability
            self.noise[i] = c.correlation * self.noise[i] + np.sqrt(1 - c.correlation**2) * fresh
            self.noise[i, jumps] += rng.choice([-1.0, 1.0], jumps.sum()) * c.jump_scale
        return np.clip(gait + self.noise, -1.0, 1.0)
