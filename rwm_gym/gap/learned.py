"""A learned correction for what no effect names: a residual joint torque, linear in each joint's state, per group.

When the gap stays significantly above the noise floor after the named effects (or nothing is named), the rest is
learned, not named: every actuated joint j of group g gets the torque

    tau_j = w_g . (q_j - default_j,  target_j - q_j,  qdot_j,  1)

(one weight vector per group: by default the joint types, HAA / HFE / KFE across legs, grouped by the spec's joint
names as in `gap.scope`), added in re-simulation as `qfrc_applied` held over each policy step
(`resim.TorqueCorrection`). Its weights read as physics: N·m per rad of deflection from the default pose (a spring),
per rad of position error (a gain), per rad/s (a damper), and N·m (an offset).

The weights are fitted like the named effects: least squares (`scipy.optimize.least_squares`) of the normalised state
error of re-simulated `FitConfig.fit_horizon`-step windows of the fitting episodes (the effects' own windows), through
the simulator, and judged by the held-out gap. Why this form and not a network fitted to one-step misses: a small
effect moves the state by less than the sensor noise in one policy step, and the simulator's response to small probe
torques is far from linear (contacts stick), so one-step misses say little about it; over several steps it rises
above the noise, and a few weights per joint type that read as physics can be fitted through the simulator itself
(figures: the docs' Results, "Gap workflow").
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import save_file
from scipy import optimize

from rwm_gym.atomic import atomic_write
from rwm_gym.gap.fit import BLOW_UP_RESIDUAL
from rwm_gym.gap.resim import Resimulator, SimulationDiverged, Windows, normalised_residual
from rwm_gym.gap.scope import joint_groups
from rwm_gym.physics.params import PhysicsParams

FORMAT = "rwm-gym-learned-correction"
VERSION = 2
FEATURES: tuple[tuple[str, str], ...] = (
    ("deflection", "N·m/rad"),
    ("position_error", "N·m/rad"),
    ("velocity", "N·m·s/rad"),
    ("offset", "N·m"),
)
"""The torque's terms, in the order of `joint_features`, with the unit of each weight."""


@dataclass(frozen=True)
class LearnedCorrectionConfig:
    """The residual torque and its fit."""

    scope: str = "joint_type"
    """Joint grouping with one weight vector per group (`gap.scope.joint_groups`: "joint_type", "leg" or "joint");
    "global", or a spec whose names do not group, gives one weight vector for every joint."""
    max_evaluations: int = 40
    """Cap on re-simulations of the least-squares search (finite differences included)."""
    weight_scales: tuple[float, ...] = (20.0, 20.0, 2.0, 5.0)
    """Typical size of each weight (units of `FEATURES`): the search's step and trust region are in these units."""


def joint_features(joint_pos: np.ndarray, joint_vel: np.ndarray, target: np.ndarray, default: np.ndarray) -> np.ndarray:
    """(..., A, 4) per joint: q - default pose, target - q, q̇, 1 (rad, rad, rad/s, 1)."""
    return np.stack([joint_pos - default, target - joint_pos, joint_vel, np.ones_like(joint_pos)], axis=-1)


def group_matrix(spec, scope: str) -> tuple[list[str], np.ndarray]:
    """Group names and the (A, G) 0/1 matrix that gives each actuated joint its group's weights."""
    groups = joint_groups(spec, scope) if scope != "global" else {}
    groups = groups or {"all": list(range(spec.action_dim))}
    matrix = np.zeros((spec.action_dim, len(groups)))
    for g, joints in enumerate(groups.values()):
        matrix[joints, g] = 1.0
    return list(groups), matrix


class LinearResidualTorque:
    """The fitted torque as a `resim.TorqueCorrection`: weights (G, 4) per group named in `groups`, joints -> groups by
    `membership` (A, G)."""

    def __init__(self, weights: np.ndarray, membership: np.ndarray, default: np.ndarray, groups: list[str]):
        self.weights, self.membership, self.default = np.asarray(weights), membership, default
        self.groups = list(groups)

    def start(self, n: int) -> None:
        pass  # no history: the torque depends on the current joint state only

    def torque(self, joint_pos: np.ndarray, joint_vel: np.ndarray, target: np.ndarray) -> np.ndarray:
        features = joint_features(joint_pos, joint_vel, target, self.default)  # (n, A, 4)
        return np.einsum("naf,af->na", features, self.membership @ self.weights)


def fit_learned_correction(
    resim: Resimulator,
    train: Windows,
    params: PhysicsParams,
    config: LearnedCorrectionConfig = LearnedCorrectionConfig(),
) -> tuple[LinearResidualTorque, dict]:
    """Fit the residual torque on top of `params` to the training windows (the named effects' fitting windows).

    Returns the correction and its training figures: the groups, the weights per group and term (with units), the
    training cost (mean squared normalised error) before and after, the re-simulations spent and the points where
    the simulation blew up (each with MuJoCo's reason)."""
    spec = resim.spec
    names, membership = group_matrix(spec, config.scope)
    default = np.asarray(spec.actuator.default_pose)
    scales = np.asarray(config.weight_scales)
    size = len(train) * train.horizon * spec.state_dim
    rejected: list[str] = []

    def correction(x: np.ndarray) -> LinearResidualTorque:
        return LinearResidualTorque(x.reshape(len(names), len(FEATURES)) * scales, membership, default, names)

    def residual(x: np.ndarray) -> np.ndarray:
        try:
            sim = resim.rollout(train, params, correction=correction(x))
        except SimulationDiverged as err:
            rejected.append(err.reason)
            return np.full(size, BLOW_UP_RESIDUAL)
        return normalised_residual(spec, sim, train.target).ravel()

    start = np.zeros(len(names) * len(FEATURES))
    before = float(np.mean(residual(start) ** 2))
    if rejected:
        raise SimulationDiverged(f"the simulator blows up without a correction: {rejected[0]}", np.zeros(0, bool))
    found = optimize.least_squares(residual, start, diff_step=1e-2, max_nfev=config.max_evaluations)
    fitted = correction(found.x)
    weights = {
        g: {f"{term} ({unit})": round(float(w), 4) for (term, unit), w in zip(FEATURES, row)}
        for g, row in zip(names, fitted.weights)
    }
    return fitted, {
        "groups": names,
        "weights": weights,
        "train_cost_before": before,
        "train_cost_after": float(np.mean(found.fun**2)),
        "evaluations": int(found.nfev) + 1,
        "rejected": rejected,
    }


def save_correction(correction: LinearResidualTorque, path: Path, config: LearnedCorrectionConfig, spec) -> None:
    """safetensors weights (G, 4) and the joints' group matrix, with the format, config, joint and group names and
    the terms in the JSON metadata."""
    meta = {
        "format": FORMAT,
        "version": str(VERSION),
        "config": json.dumps(asdict(config)),
        "joints": json.dumps(list(spec.actuator.joints)),
        "groups": json.dumps(correction.groups),
        "features": json.dumps([f"{term} ({unit})" for term, unit in FEATURES]),
    }
    tensors = {
        "weights": torch.as_tensor(correction.weights, dtype=torch.float64).contiguous(),
        "membership": torch.as_tensor(correction.membership, dtype=torch.float64).contiguous(),
    }
    atomic_write(path, lambda tmp: save_file(tensors, tmp, metadata=meta))


def load_correction(path: str | Path, spec) -> LinearResidualTorque:
    """A saved correction for `spec`'s robot (its joints must match, in order); reads tensors and JSON only."""
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as f:
        meta = f.metadata() or {}
        if meta.get("format") != FORMAT or meta.get("version") != str(VERSION):
            raise ValueError(
                f"{path}: not a learned correction of version {VERSION} (format {meta.get('format')!r}, "
                f"version {meta.get('version')!r})"
            )
        if json.loads(meta["joints"]) != list(spec.actuator.joints):
            raise ValueError(f"{path}: its joints differ from the task spec's {spec.name!r}")
        weights, membership = f.get_tensor("weights").numpy(), f.get_tensor("membership").numpy()
    return LinearResidualTorque(weights, membership, np.asarray(spec.actuator.default_pose), json.loads(meta["groups"]))
