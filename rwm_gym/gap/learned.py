"""A learned correction for what no effect names: a small network of the missing joint torque, actuator-network style.

When the gap stays significantly above the noise floor after the named effects (or nothing is named), the rest is
learned, not named: a multilayer perceptron shared by all joints maps one joint's recent history (joint position
relative to the default pose, position error target - q, joint velocity, at the last `history` policy steps) plus a
one-hot of the joint to the torque that joint misses (N·m). This is the actuator network of Hwangbo et al. (2019)
used as a residual on top of the (corrected) simulator.

Training data come from the measured fitting episodes (never the held-out ones): from each measured row the
simulator steps one policy step with the measured action, which gives the base and joint velocities it misses, and
again with a probe torque on each joint, which gives those velocities' response to a joint torque there (contacts
included). The network is fitted so that response @ torque matches the missing velocities (least squares, each
channel in units of the spec's state std; why the base velocities too: `LearnedCorrectionConfig.observed`). The
correction is applied in re-simulation as a joint torque (`qfrc_applied`) held over each policy step
(`resim.TorqueCorrection`), and judged by the held-out gap like any candidate. It lives in the report and
`learned_correction.safetensors`, not in the corrected MJCF.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import save_file

from rwm_gym.atomic import atomic_write
from rwm_gym.gap.resim import Resimulator, SimulationDiverged, Windows
from rwm_gym.physics.params import PhysicsParams
from rwm_gym.physics.robot import RobotLayout

FORMAT = "rwm-gym-learned-correction"
VERSION = 1


@dataclass(frozen=True)
class LearnedCorrectionConfig:
    """The residual network and its training."""

    history: int = 3
    """Policy steps of joint history per input (the current one and history-1 before)."""
    stride: int = 2
    """Rows between the measured rows used for training (every row: 1)."""
    hidden: int = 32
    """Width of the two hidden layers."""
    iterations: int = 1500
    """Adam steps (full batch)."""
    lr: float = 3e-3
    weight_decay: float = 1e-3
    observed: tuple[str, ...] = ("base_lin_vel", "base_ang_vel", "joint_vel")
    """State groups whose one-step miss the torque is fitted to, each in units of the spec's state std. The joint
    velocities alone cannot see a torque in a stance leg (the contact holds the joint still and the body moves
    instead), and fitted so the network put arbitrary torques there: on two of four grid cases the held-out gap grew,
    up to twice as large. Adding the base velocities makes that torque observable."""
    seed: int = 0


class ResidualTorqueNet(torch.nn.Module):
    """Per-joint history features (B, A, F) -> missing torque (B, A) N·m; one network for every joint."""

    def __init__(self, features: int, hidden: int):
        super().__init__()
        self.net = torch.nn.Sequential(torch.nn.Linear(features, hidden), torch.nn.Tanh(),
                                       torch.nn.Linear(hidden, hidden), torch.nn.Tanh(), torch.nn.Linear(hidden, 1))
        self.register_buffer("mean", torch.zeros(features))
        self.register_buffer("std", torch.ones(features))
        self.register_buffer("scale", torch.ones(()))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net((x - self.mean) / self.std).squeeze(-1) * self.scale


def joint_features(joint_pos: np.ndarray, joint_vel: np.ndarray, target: np.ndarray, default: np.ndarray) -> np.ndarray:
    """(..., A, 3) per joint: q - default pose, target - q, q̇ (rad, rad, rad/s)."""
    return np.stack([joint_pos - default, target - joint_pos, joint_vel], axis=-1)


def with_joint_ids(history: np.ndarray) -> np.ndarray:
    """(B, A, H*3) history -> (B, A, H*3 + A) with a one-hot of the joint appended."""
    b, a, _ = history.shape
    return np.concatenate([history, np.broadcast_to(np.eye(a), (b, a, a))], axis=-1)


class LearnedTorque:
    """The trained network as a `resim.TorqueCorrection`: keeps each simulation's last `history` feature rows."""

    def __init__(self, net: ResidualTorqueNet, default: np.ndarray, history: int):
        self.net, self.default, self.history = net, default, history
        self.buffer: np.ndarray | None = None

    def start(self, n: int) -> None:
        self.buffer = None

    def torque(self, joint_pos: np.ndarray, joint_vel: np.ndarray, target: np.ndarray) -> np.ndarray:
        now = joint_features(joint_pos, joint_vel, target, self.default)  # (n, A, 3)
        if self.buffer is None:  # no history yet: repeat the first row (as in training)
            self.buffer = np.repeat(now[:, None], self.history, axis=1)
        self.buffer = np.concatenate([now[:, None], self.buffer[:, :-1]], axis=1)  # newest first
        x = with_joint_ids(self.buffer.transpose(0, 2, 1, 3).reshape(len(now), now.shape[1], -1))
        with torch.no_grad():
            return self.net(torch.as_tensor(x, dtype=torch.float32)).double().numpy()


class ConstantTorque:
    """A fixed joint torque (A,) N·m on every simulation: probes the simulator's response for `training_targets`."""

    def __init__(self, torque: np.ndarray):
        self.value = torque

    def start(self, n: int) -> None:
        pass

    def torque(self, joint_pos: np.ndarray, joint_vel: np.ndarray, target: np.ndarray) -> np.ndarray:
        return np.broadcast_to(self.value, joint_pos.shape)


def training_targets(resim: Resimulator, windows: Windows, params: PhysicsParams, history: int, probe_nm: float = 1.0,
                     observed: tuple[str, ...] = LearnedCorrectionConfig.observed
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """From one-step windows (horizon 1, warmup history-1): inputs (B, A, F), what the simulator misses after one
    policy step in the `observed` state groups (B, O) in state-std units, and their response to a joint torque held
    over that step (B, O, A) per N·m, probed with `probe_nm` on each joint in turn (contacts included)."""
    spec = resim.spec
    act = spec.actuator
    default = np.asarray(act.default_pose)
    model = resim.model(params)
    layout = RobotLayout.from_model(model, spec)
    k = windows.warmup
    targets = default + act.action_scale * np.clip(windows.actions[:, :k + 1], -1.0, 1.0)  # rows start-k .. start
    feats = joint_features(windows.qpos[:, :, layout.qpos_adr], windows.qvel[:, :, layout.dof_adr], targets,
                           default)  # (B, k+1, A, 3)
    rows = [feats[:, max(k - lag, 0)] for lag in range(history)]  # newest first, repeated where history is short
    x = with_joint_ids(np.stack(rows, axis=2).reshape(len(windows), spec.action_dim, -1))
    columns = np.concatenate([np.arange(spec.state_dim)[spec.state_slices[name]] for name in observed])
    scale = np.asarray(spec.state_std)[columns]
    free = resim.rollout(windows, params, horizon=1)[:, 0, columns] / scale
    missing = windows.target[:, 0, columns] / scale - free
    response = np.empty((len(windows), len(columns), spec.action_dim))
    for j in range(spec.action_dim):
        probe = np.zeros(spec.action_dim)
        probe[j] = probe_nm
        pushed = resim.rollout(windows, params, horizon=1, correction=ConstantTorque(probe))[:, 0, columns] / scale
        response[:, :, j] = (pushed - free) / probe_nm
    return x, missing, response


def train_correction(x: np.ndarray, missing: np.ndarray, response: np.ndarray, config: LearnedCorrectionConfig
                     ) -> tuple[ResidualTorqueNet, dict]:
    """Fit the network so that the simulator's response to its torque, response @ torque(x), matches what the
    simulator misses in the observed state groups (least squares); returns it and its training figures."""
    torch.manual_seed(config.seed)
    xt = torch.as_tensor(x, dtype=torch.float32)
    yt, bt = torch.as_tensor(missing, dtype=torch.float32), torch.as_tensor(response, dtype=torch.float32)
    net = ResidualTorqueNet(x.shape[-1], config.hidden)
    flat = xt.reshape(-1, x.shape[-1])
    net.mean.copy_(flat.mean(0))
    net.std.copy_(flat.std(0).clamp_min(1e-6))
    # torque scale: the least-squares torque of a typical response
    typical = torch.linalg.pinv(bt.mean(0)) @ yt.T
    net.scale.copy_(typical.std().clamp(1e-3, 1e3))
    opt = torch.optim.Adam(net.parameters(), lr=config.lr, weight_decay=config.weight_decay)

    def loss_fn() -> torch.Tensor:
        return ((torch.einsum("bij,bj->bi", bt, net(xt)) - yt) ** 2).mean()

    for _ in range(config.iterations):
        opt.zero_grad()
        loss = loss_fn()
        loss.backward()
        opt.step()
    with torch.no_grad():
        final, torque = float(loss_fn()), net(xt)
    return net, {"samples": int(missing.shape[0]), "missing_rms": float(np.sqrt((missing**2).mean())),
                 "fit_rmse": float(np.sqrt(final)), "torque_rms_nm": float(torque.pow(2).mean().sqrt())}


def fit_learned_correction(resim: Resimulator, train: Windows, params: PhysicsParams,
                           config: LearnedCorrectionConfig = LearnedCorrectionConfig()
                           ) -> tuple[LearnedTorque, ResidualTorqueNet, dict]:
    """Train the residual torque network on one-step windows of the fitting episodes, on top of `params`."""
    for _ in range(3):  # leave out rows where the simulator itself blows up (rare; the count is reported)
        try:
            x, missing, response = training_targets(resim, train, params, config.history, observed=config.observed)
            break
        except SimulationDiverged as err:
            train = train.subset(~err.windows)
    else:
        raise SimulationDiverged("the simulator keeps blowing up on the training rows", np.zeros(0, bool))
    net, info = train_correction(x, missing, response, config)
    return LearnedTorque(net, np.asarray(resim.spec.actuator.default_pose), config.history), net, info


def save_correction(net: ResidualTorqueNet, path: Path, config: LearnedCorrectionConfig, joints: list[str]) -> None:
    """safetensors weights with the format, config and joint order in the JSON metadata."""
    meta = {"format": FORMAT, "version": str(VERSION), "config": json.dumps(asdict(config)),
            "joints": json.dumps(list(joints))}
    tensors = {k: v.contiguous() for k, v in net.state_dict().items()}
    atomic_write(path, lambda tmp: save_file(tensors, tmp, metadata=meta))
